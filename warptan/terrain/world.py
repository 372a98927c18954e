"""Worlds that are not the map: the simulated ground a flight sees when the on-board DEM is another product.

Every real flight reads a DEM of another source and date than the ground below: it lacks the relief under its
post spacing, carries vertical errors of metres that are correlated over hundreds of metres to kilometres, a
bias, and (for a laser) canopy and buildings it does not hold. :class:`WorldModel` builds such a world from the
filter's map (the DEM), seeded and reproducible; the map stays the DEM. In the world's grid (``refine`` world
posts per map post on each axis, the same NED frame and origin):

``world = bilinear(map) + relief − error − bias + clutter``

* **Sub-post relief** (``relief_rms_m``, ``relief_slope``): a Gaussian random field whose power spectrum is the
  map's own, extrapolated past its Nyquist band: the map's radially averaged periodogram (Hann window, plane
  removed) is fitted as ``P(k) = A k^-β`` between 1/8 and 1/2 of its Nyquist wavenumber (below the roll-off of its
  posts' interpolation), and the field carries ``A k^-β`` for the wavenumbers outside the map's band
  (``|k_n| > 1/(2 dn)`` or ``|k_e| > 1/(2 de)``) up to the world's Nyquist. ``relief_rms_m = "auto"`` takes the
  fitted amplitude (its RMS is reported in :attr:`World.parts`), a number sets the RMS; ``relief_slope = "auto"``
  the fitted β (clipped to [2, 5]), a number sets it.
* **Correlated error** of an independent DEM product (``error_rms_m``, ``error_corr_m``): a stationary Gaussian
  random field with covariance ``error_rms² · exp(−(r / error_corr_m)²)``, made by filtering white noise in the
  Fourier domain on a grid padded by three correlation lengths (no wrap-around correlation). The map reads
  ``world + error``. Published accuracies to set it from, as 90 % linear errors (LE90; Gaussian RMS = LE90 / 1.645):
  SRTM: specification 16 m absolute, 10 m relative; measured absolute 5.6–9.0 m by continent (Farr et al. 2007,
  Rev. Geophys. 45 RG2004; Rodríguez et al. 2006, PE&RS 72(3)). Copernicus DEM GLO-30: < 4 m absolute (its product
  handbook's specification). DTED level 1 / level 2: 30 m / 18 m absolute (MIL-PRF-89020B). Correlation lengths
  are not published as single numbers; errors of these products are reported correlated over hundreds of metres
  to kilometres, so ``error_corr_m`` is the user's assumption (warptan's study sweeps it).
* **Bias** (``bias_m``): the map reads ``bias_m`` higher than the world everywhere.
* **Clutter** (``clutter_height_m``, ``clutter_fraction``, ``clutter_patch_m``): canopy or buildings as a height
  offset over a random mask covering ``clutter_fraction`` of the ground in patches of about ``clutter_patch_m``
  (a smooth field thresholded at its quantile). Every sensor of the simulation sees the world surface, clutter
  included (a laser's first return; a radar altimeter reads the canopy too, to first order).

``seed`` fixes the realisation (``-1``: each run's own seed, so its runs cannot share one batched filter).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from dataclasses import dataclass

import numpy as np

from warptan.terrain.grid import Terrain
from warptan.terrain.raster import MAX_POSTS, TerrainError

AUTO = "auto"
RELIEF_SLOPE_RANGE = (2.0, 5.0)
"""Spectral slopes β of the sub-post relief a fit may give (2-D power spectrum ∝ k^-β); natural terrain lies
around 3–4."""
MAX_REFINE = 8
"""Most world posts per map post on one axis."""


def _number(low: float, high: float, whole: bool = False):
    """A finite number (a whole one with ``whole``) in [low, high]."""
    def ok(v):
        if isinstance(v, bool) or not isinstance(v, int if whole else (int, float)):
            return False
        return math.isfinite(v) and low <= v <= high
    return ok


_RULES = {
    "relief_rms_m": (_number(0.0, 1e3), "must be 'auto' (extrapolated from the map's spectrum) or in [0, 1000] m"),
    "relief_slope": (_number(*RELIEF_SLOPE_RANGE),
                     f"must be 'auto' or in [{RELIEF_SLOPE_RANGE[0]:g}, {RELIEF_SLOPE_RANGE[1]:g}]"),
    "error_rms_m": (_number(0.0, 1e3), "must be in [0, 1000] m"),
    "error_corr_m": (_number(0.0, 1e6), "must be in [0, 1e+06] m"),
    "bias_m": (_number(-1e4, 1e4), "must be within ±10000 m"),
    "clutter_height_m": (_number(0.0, 1e3), "must be in [0, 1000] m"),
    "clutter_fraction": (_number(0.0, 1.0), "must be in [0, 1]"),
    "clutter_patch_m": (lambda v: _number(0.0, 1e6)(v) and v > 0, "must be in (0, 1e+06] m"),
    "refine": (_number(1, MAX_REFINE, whole=True), f"must be a whole number in [1, {MAX_REFINE}]"),
    "seed": (_number(-1, 2**32 - 1, whole=True), "must be ≥ 0, or -1 (each run's own seed)"),
}
"""Per field: (valid?, what it must be). ``"auto"`` is valid where the field allows text (relief)."""


@dataclass(frozen=True)
class WorldModel:
    """How the simulated world differs from the filter's map (see the module's text for the equations)."""

    relief_rms_m: float | str = 0.0
    """RMS of the sub-post relief, m; ``"auto"``: extrapolated from the map's spectrum; 0: none."""
    relief_slope: float | str = AUTO
    """Spectral slope β of the relief (2-D PSD ∝ k^-β); ``"auto"``: fitted on the map."""
    error_rms_m: float = 0.0
    """RMS of the map's correlated vertical error, m."""
    error_corr_m: float = 0.0
    """Its correlation length L, m (covariance ∝ exp(−(r/L)²)); at least one map post when error_rms_m > 0."""
    bias_m: float = 0.0
    """The map reads this much higher than the world, m."""
    clutter_height_m: float = 0.0
    """Height of canopy / buildings over the clutter mask, m."""
    clutter_fraction: float = 0.0
    """Fraction of the ground under clutter, [0, 1]."""
    clutter_patch_m: float = 60.0
    """Size of the clutter patches (correlation length of the field thresholded into the mask), m."""
    refine: int = 3
    """World posts per map post on each axis (the world's grid resolves the relief the map lacks)."""
    seed: int = 0
    """Realisation of the random fields; -1: each run's own seed."""

    @property
    def active(self) -> bool:
        """True when the world differs from the map at all."""
        return bool(self.relief_rms_m == AUTO or self.relief_rms_m or self.error_rms_m or self.bias_m
                    or (self.clutter_height_m and self.clutter_fraction))

    @property
    def per_seed(self) -> bool:
        """Each run draws its own world (``seed = -1``)."""
        return self.active and self.seed < 0

    @classmethod
    def from_config(cls, table: dict) -> WorldModel:
        """From a scenario's ``[world]`` table (validated)."""
        return cls(**{f.name: table[f.name] for f in dataclasses.fields(cls) if f.name in table})

    def problems(self, map_spacing_m: tuple[float, float] | None = None) -> list[str]:
        """Every problem of the model (empty: usable; the one place its ranges are stated, scenario files
        included); with the map's post spacing, also the correlation and patch lengths against it."""
        p = []
        for name, (ok, rule) in _RULES.items():
            value = getattr(self, name)
            try:
                good = value == AUTO if isinstance(value, str) else bool(ok(value))
            except TypeError:
                good = False
            if not good:
                p.append(f"world.{name} = {value!r} {rule}")
        if map_spacing_m is not None and not p:
            post = max(map_spacing_m)
            if self.error_rms_m and self.error_corr_m < post:
                p.append(f"world.error_corr_m = {self.error_corr_m:g} m is shorter than one post of the map "
                         f"({post:.4g} m): an error correlated over less than a post is noise per post; use "
                         "terrain.map_noise_m for that, or a correlation length ≥ the post spacing")
            if self.clutter_height_m and self.clutter_fraction and self.clutter_patch_m < post / self.refine:
                p.append(f"world.clutter_patch_m = {self.clutter_patch_m:g} m is shorter than one world post "
                         f"({post / self.refine:.4g} m)")
        return p

    def describe(self) -> str:
        """A short text of what differs (for names and tables)."""
        parts = []
        if self.relief_rms_m == AUTO or self.relief_rms_m:
            rms = "auto" if self.relief_rms_m == AUTO else f"{self.relief_rms_m:g} m"
            slope = "" if self.relief_slope == AUTO else f", β {self.relief_slope:g}"
            parts.append(f"relief {rms}{slope}")
        if self.error_rms_m:
            parts.append(f"error {self.error_rms_m:g} m / {self.error_corr_m:g} m")
        if self.bias_m:
            parts.append(f"bias {self.bias_m:+g} m")
        if self.clutter_height_m and self.clutter_fraction:
            parts.append(f"clutter {self.clutter_height_m:g} m over {100 * self.clutter_fraction:g} %")
        return ", ".join(parts) or "the map"

    def build(self, dem: Terrain, seed: int = 0) -> World:
        """The world of this model over ``dem`` (the filter's map); ``seed`` is used when ``self.seed`` is -1."""
        problems = self.problems((dem.dn, dem.de))
        if problems:
            raise TerrainError("; ".join(problems))
        r = self.refine
        rows, cols = (dem.shape[0] - 1) * r + 1, (dem.shape[1] - 1) * r + 1
        if rows * cols > MAX_POSTS:
            raise TerrainError(f"world of {dem.name}: {rows}×{cols} posts at refine = {r} exceed the limit "
                               f"{MAX_POSTS}; use a smaller refine or a smaller DEM")
        dn, de = dem.dn / r, dem.de / r
        north = dem.n0 + np.arange(rows) * dn
        east = dem.e0 + np.arange(cols) * de
        nn, ee = np.meshgrid(north, east, indexing="ij")
        base = dem.height_at(nn.ravel(), ee.ravel()).reshape(rows, cols)
        rng = np.random.default_rng([self.seed if self.seed >= 0 else int(seed), 0x5EED_0F_3A7])
        parts: dict[str, float] = {}
        h = base.copy()
        if self.relief_rms_m == AUTO or self.relief_rms_m:
            relief, fit = self._relief(dem, (rows, cols), (dn, de), rng)
            h += relief
            parts.update(relief_rms_m=_rms(relief), relief_slope=fit["slope"], relief_fit_amplitude=fit["amplitude"])
        if self.error_rms_m:
            error = self.error_rms_m * _unit_field((rows, cols), (dn, de), _gaussian_psd(self.error_corr_m), rng,
                                                   pad_m=3.0 * self.error_corr_m)
            h -= error
            parts["error_rms_m"] = _rms(error)
        if self.bias_m:
            h -= self.bias_m
        if self.clutter_height_m and self.clutter_fraction:
            patches = _unit_field((rows, cols), (dn, de), _gaussian_psd(self.clutter_patch_m), rng,
                                  pad_m=3.0 * self.clutter_patch_m)
            mask = patches > np.quantile(patches, 1.0 - self.clutter_fraction)
            h += self.clutter_height_m * mask
            parts["clutter_fraction"] = float(mask.mean())
        h[np.isnan(base)] = np.nan
        diff = base - h
        parts["map_minus_world_rms_m"] = _rms(diff)
        return World(h, dem.n0, dem.e0, dn, de, crs_wkt=dem.crs_wkt, origin_xy=dem.origin_xy,
                     name=f"{dem.name} + world({self.describe()})", description=dem.description,
                     valid_range_m=(-math.inf, math.inf), base=dem, model=self, parts=parts)

    def _relief(self, dem: Terrain, shape, spacing, rng) -> tuple[np.ndarray, dict]:
        """The sub-post relief field and the spectral fit it used (the DEM's spectrum is fitted only for what is
        ``"auto"``)."""
        fit = fit_spectrum(dem) if AUTO in (self.relief_rms_m, self.relief_slope) else {"amplitude": math.nan}
        slope = fit["slope"] if self.relief_slope == AUTO else float(self.relief_slope)
        band = _outside_band(shape, spacing, (dem.dn, dem.de))
        kn, ke = _wavenumbers(shape, spacing)
        grid_psd = np.where(band, np.maximum(np.hypot(kn[:, None], ke[None, :]), 1e-12) ** (-slope), 0.0)
        unit = _unit_field(shape, spacing, lambda k: grid_psd, rng, pad_m=0.0)  # unpadded: the grid's own k
        if self.relief_rms_m == AUTO:  # the fitted amplitude over the band the world adds
            dk = 1.0 / (shape[0] * spacing[0]) / (shape[1] * spacing[1])
            rms = math.sqrt(max(float(fit["amplitude"] * grid_psd.sum() * dk), 0.0))
        else:
            rms = float(self.relief_rms_m)
        return rms * unit, {"slope": slope, "amplitude": fit["amplitude"]}


@dataclass(eq=False)
class World(Terrain):
    """A simulated world built by :meth:`WorldModel.build`: a :class:`~warptan.terrain.grid.Terrain` on a finer grid,
    with the map it was made from."""

    base: Terrain | None = None
    """The DEM the world was made from (the filter's map)."""
    model: WorldModel | None = None
    """How it differs from the map."""
    parts: dict = dataclasses.field(default_factory=dict)
    """Measured RMS of each part (relief, error), the relief's fitted slope and amplitude, the clutter fraction
    and the RMS of map − world over the grid (m)."""


def fit_spectrum(dem: Terrain) -> dict:
    """Fit ``P(k) = A k^-β`` to the map's radially averaged two-sided periodogram (m² per (cycle/m)², Hann
    window, best-fit plane removed, nodata filled with the mean) between 1/8 and 1/2 of its Nyquist wavenumber.
    Returns ``slope`` β (clipped to :data:`RELIEF_SLOPE_RANGE`) and ``amplitude`` A."""
    h = np.array(dem.heights_m, dtype=np.float64)
    valid = np.isfinite(h)
    h[~valid] = np.nanmean(h)
    rows, cols = h.shape
    yy, xx = np.meshgrid(np.arange(rows) * dem.dn, np.arange(cols) * dem.de, indexing="ij")
    design = np.column_stack([np.ones(h.size), yy.ravel(), xx.ravel()])
    coef, *_ = np.linalg.lstsq(design, h.ravel(), rcond=None)
    h = h - (design @ coef).reshape(h.shape)
    window = np.outer(np.hanning(rows), np.hanning(cols))
    spec = np.abs(np.fft.fft2(h * window)) ** 2 * dem.dn * dem.de / (rows * cols) / np.mean(window**2)
    kn, ke = _wavenumbers((rows, cols), (dem.dn, dem.de))
    k = np.hypot(kn[:, None], ke[None, :])
    k_nyq = 0.5 / max(dem.dn, dem.de)
    edges = np.geomspace(k_nyq / 8.0, k_nyq / 2.0, 9)
    logk, logp = [], []
    for lo, hi in itertools.pairwise(edges):
        sel = (k >= lo) & (k < hi)
        if sel.any() and np.mean(spec[sel]) > 0:
            logk.append(math.log(math.sqrt(lo * hi)))
            logp.append(math.log(float(np.mean(spec[sel]))))
    if len(logk) < 3:
        raise TerrainError(f"{dem.name}: too small to fit its height spectrum (give relief_rms_m and relief_slope)")
    slope, intercept = np.polyfit(logk, logp, 1)
    beta = float(np.clip(-slope, *RELIEF_SLOPE_RANGE))
    # the amplitude that keeps the fitted power at the band's centre with the clipped slope
    k_mid = math.exp(float(np.mean(logk)))
    amplitude = math.exp(intercept + slope * math.log(k_mid)) * k_mid**beta
    return {"slope": beta, "amplitude": float(amplitude), "fitted_slope": float(-slope)}


def _wavenumbers(shape, spacing) -> tuple[np.ndarray, np.ndarray]:
    """Wavenumbers (cycles/m) of the FFT axes of a grid (rows north, cols east)."""
    return np.fft.fftfreq(shape[0], spacing[0]), np.fft.fftfreq(shape[1], spacing[1])


def _outside_band(shape, spacing, map_spacing) -> np.ndarray:
    """Wavenumbers of the world grid beyond the map's Nyquist band on either axis."""
    kn, ke = _wavenumbers(shape, spacing)
    return (np.abs(kn)[:, None] > 0.5 / map_spacing[0]) | (np.abs(ke)[None, :] > 0.5 / map_spacing[1])


def _gaussian_psd(corr_m: float):
    """Power spectrum (up to a constant) of the covariance exp(−(r/L)²): exp(−π² L² k²)."""
    return lambda k: np.exp(-((math.pi * corr_m * k) ** 2))


def _unit_field(shape, spacing, psd, rng: np.random.Generator, pad_m: float) -> np.ndarray:
    """A stationary Gaussian field of unit variance with power spectrum ∝ ``psd(|k|)`` on a grid of ``shape``
    (white noise filtered in the Fourier domain on a grid padded by ``pad_m`` on each axis, then cropped)."""
    pad = (math.ceil(pad_m / spacing[0]), math.ceil(pad_m / spacing[1]))
    big = (shape[0] + 2 * pad[0], shape[1] + 2 * pad[1])
    kn, ke = _wavenumbers(big, spacing)
    amplitude = np.sqrt(psd(np.hypot(kn[:, None], ke[None, :])))
    field = np.fft.ifft2(np.fft.fft2(rng.standard_normal(big)) * amplitude).real
    # the variance of filtered unit white noise: mean of |amplitude|² over the frequency grid
    variance = float(np.mean(amplitude**2))
    if variance <= 0:
        return np.zeros(shape)
    return field[pad[0]:pad[0] + shape[0], pad[1]:pad[1] + shape[1]] / math.sqrt(variance)


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.nanmean(a**2)))
