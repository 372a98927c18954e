"""Generated terrains (:meth:`warptan.terrain.grid.Terrain.synthetic`): fractal surfaces with a power-law spectrum,
deterministic in their seed."""

from __future__ import annotations

import math

import numpy as np

from warptan.terrain.raster import TerrainError, check_spacing

SYNTHETIC_KINDS = ("rugged", "flat")


def synthetic_heights(kind: str, size_m: float, spacing: float, seed: int):
    """The heights of :meth:`~warptan.terrain.grid.Terrain.synthetic` (``kind``, ``size_m``, ``spacing``,
    ``seed`` as there), half the side (m), and the checked spacing and size.

    Raises:
        TerrainError: an unknown kind, or a size and spacing of fewer than 8 or more than 60 M posts a side².
    """
    if kind not in SYNTHETIC_KINDS:
        raise TerrainError(f"unknown synthetic terrain kind {kind!r}; choose one of {', '.join(SYNTHETIC_KINDS)}")
    spacing = check_spacing(spacing)
    size_m = check_spacing(size_m, "size_m")
    n = math.floor(size_m / spacing) + 1
    if n < 8:
        raise TerrainError(f"size_m={size_m} with spacing={spacing} gives only {n} posts a side (need ≥ 8)")
    if n * n > 60_000_000:
        raise TerrainError(f"size_m={size_m} with spacing={spacing} gives {n}×{n} posts; use a larger spacing")
    rng = np.random.default_rng(np.random.PCG64(seed))
    if kind == "rugged":
        heights = 200.0 + 800.0 * _fractal(rng, n, spacing, beta=2.3, longest_m=12_000.0)
    else:
        heights = 150.0 + 6.0 * _fractal(rng, n, spacing, beta=2.0, longest_m=8_000.0)
    return heights, 0.5 * (n - 1) * spacing, spacing, size_m


def _fractal(rng: np.random.Generator, n: int, spacing: float, beta: float, longest_m: float) -> np.ndarray:
    """An (n, n) surface in [0, 1] with a power-law spectrum ``|k|^-beta`` above wavelength ``longest_m``."""
    m = 1 << math.ceil(math.log2(n))
    k = np.fft.fftfreq(m, d=spacing)
    kk = np.hypot(*np.meshgrid(k, k, indexing="ij"))
    k0 = 1.0 / longest_m
    amp = (kk * kk + k0 * k0) ** (-beta / 2.0)
    amp[0, 0] = 0.0
    noise = rng.standard_normal((m, m)) + 1j * rng.standard_normal((m, m))
    z = np.fft.ifft2(noise * amp).real[:n, :n]
    z -= z.min()
    return z / z.max()
