"""Argument checks shared by the modules: one message format for bad numbers, and the error of the navigation
layer.

Each layer has its error type, all ``ValueError`` subclasses with one-line messages naming the input:
:class:`FilterError` (IMU samples, states, measurements, rays, filter and sensor arguments),
:class:`~warptan.terrain.raster.TerrainError` (DEM files and terrain arguments),
:class:`~warptan.sim.scenario_config.ScenarioError` (scenario files, overrides, seeds, memory, flights) and
:class:`~warptan.outputs.OutputError` (output folders). The command line turns each into one line and exit status 2."""

from __future__ import annotations

import math
import numbers
import os


class FilterError(ValueError):
    """A bad input to the navigation layer (filter, INS, IMU, sensors, measurement models, ray casts, trajectories);
    the message names the argument or sample and the value."""


class FilterWarning(UserWarning):
    """A navigation-layer setting that runs but whose results are not meaningful (e.g. two particles)."""


FLOAT32_MAX = 3.4028234663852886e38
"""Largest finite float32."""
LOCAL_FRAME_M = 1e7
"""Largest NED coordinate a position or a terrain origin may have, m (a local frame; float32 keeps 1 m there)."""


def check_positive(value, name: str, error: type[Exception] = FilterError) -> float:
    """``value`` as a float if it is a finite number > 0, else ``error`` naming ``name`` and the value."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise error(f"{name} must be a positive number, got {value!r}") from None
    if not (math.isfinite(number) and number > 0):
        raise error(f"{name} must be a positive number, got {value!r}")
    return number


def check_seed(value, name: str = "seed", error: type[Exception] = FilterError) -> int:
    """``value`` as an int if it is a whole number ≥ 0 (a Python or NumPy integer, not a bool or a float, which
    would be truncated silently), else ``error`` naming ``name`` and the value."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 0:
        raise error(f"{name} must be a whole number ≥ 0, got {value!r}")
    return int(value)


def check_float32(values, name: str, error: type[Exception] = FilterError) -> None:
    """Refuse values that are not finite, or finite in float64 but beyond float32 (the device's precision), where
    they would silently become inf or NaN; the message names ``name`` and the first bad value."""
    import numpy as np

    a = np.asarray(values, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~(np.abs(a) <= FLOAT32_MAX)
    if bad.any():
        first = a[bad].ravel()[0]
        why = "not finite" if not np.isfinite(first) else "beyond float32 range (±3.4e38)"
        raise error(f"{name}: {int(bad.sum())} value(s) {why}, first {first!r}")


def host_memory_available() -> float:
    """Bytes of host memory available now (Linux MemAvailable; elsewhere the physical memory)."""
    host = float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    host = float(line.split()[1]) * 1024.0
    except OSError:
        pass
    return host
