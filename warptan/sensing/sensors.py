"""Sensors: scan patterns, the point-cloud sensor, the radar altimeter and the barometer (design notes §5).

A scan pattern is M unit directions ``d_j`` in the sensor frame (FRD = body frame; nadir is +z). The
point-cloud sensor casts ``R_true d_j`` from ``p_true`` against the *truth* terrain: range ``r_j`` plus
Gaussian noise, point ``c_j = r_j d_j``; a ray with no hit (or beyond the maximum range) is invalid and
stays NaN. Noise comes from a ``numpy.random.Generator`` the caller passes (explicit seeding).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warptan.checks import FilterError
from warptan.device import upload
from warptan.nav.frames import check_unit_quat
from warptan.terrain.raycast import RayCaster, raycast_pattern


class ScanPattern:
    """M unit directions in the sensor frame (FRD).

    Args:
        dirs_s: (M, 3) directions; normalised here. Zero-length, non-finite or an empty set is an error.
        name: A label for reports.
    """

    def __init__(self, dirs_s, name: str = "custom"):
        d = np.asarray(dirs_s, dtype=np.float64)
        if d.ndim != 2 or d.shape[1] != 3:
            raise FilterError(f"scan pattern directions must have shape (M, 3), got {d.shape}")
        if len(d) == 0:
            raise FilterError("scan pattern is empty: it needs at least one direction")
        norm = np.linalg.norm(d, axis=1)
        bad = ~np.isfinite(norm) | (norm < 1e-9)
        if bad.any():
            raise FilterError(f"scan pattern has {bad.sum()} zero-length or non-finite directions "
                             f"(first at index {int(np.argmax(bad))})")
        self.dirs_s = d / norm[:, None]
        """(M, 3) unit directions, sensor frame."""
        self.name = name
        self._device_dirs: dict[str, wp.array] = {}

    @property
    def m(self) -> int:
        """Number of directions."""
        return len(self.dirs_s)

    @classmethod
    def grid(cls, nx: int = 10, ny: int = 10, half_angle_deg: tuple[float, float] | float = 30.0) -> ScanPattern:
        """A rectangular ``nx × ny`` grid around nadir: ``d ∝ (tan a_x, tan a_y, 1)`` with ``a_x`` (along
        track, about the y axis) in ±half_angle[0] and ``a_y`` (across track) in ±half_angle[1], degrees.
        The footprint on flat ground is a rectangular grid. The default is the scenarios' 10×10 over ±30°."""
        hx, hy = (half_angle_deg, half_angle_deg) if np.isscalar(half_angle_deg) else half_angle_deg
        if nx < 1 or ny < 1:
            raise FilterError(f"grid pattern needs nx, ny ≥ 1, got {nx}×{ny}")
        for h in (hx, hy):
            if not 0.0 <= h < 90.0:
                raise FilterError(f"half angle must be in [0, 90) degrees, got {h}")
        ax = np.radians(np.linspace(-hx, hx, nx)) if nx > 1 else np.zeros(1)
        ay = np.radians(np.linspace(-hy, hy, ny)) if ny > 1 else np.zeros(1)
        gx, gy = np.meshgrid(np.tan(ax), np.tan(ay), indexing="ij")
        d = np.stack([gx.ravel(), gy.ravel(), np.ones(gx.size)], axis=1)
        return cls(d, name=f"grid {nx}x{ny} ±{hx:g}°/±{hy:g}°")

    @classmethod
    def ring(cls, n: int = 32, half_angle_deg: float = 30.0) -> ScanPattern:
        """``n`` directions on a cone of ``half_angle_deg`` around nadir (a conical scanner)."""
        if n < 1:
            raise FilterError(f"ring pattern needs n ≥ 1, got {n}")
        if not 0.0 < half_angle_deg < 90.0:
            raise FilterError(f"ring half angle must be in (0, 90) degrees, got {half_angle_deg}")
        az = 2.0 * np.pi * np.arange(n) / n
        s = np.sin(np.radians(half_angle_deg))
        d = np.stack([s * np.cos(az), s * np.sin(az), np.full(n, np.cos(np.radians(half_angle_deg)))], axis=1)
        return cls(d, name=f"ring {n} at {half_angle_deg:g}°")

    @classmethod
    def nadir(cls) -> ScanPattern:
        """The single nadir ray (+z)."""
        return cls([[0.0, 0.0, 1.0]], name="nadir")

    def device_dirs(self, device) -> wp.array:
        """The directions as a (M,) vec3 array on ``device`` (cached)."""
        key = str(device)
        if key not in self._device_dirs:
            self._device_dirs[key] = wp.array(self.dirs_s.astype(np.float32), dtype=wp.vec3, device=device)
        return self._device_dirs[key]


MAX_RANGE_M = 1e6
"""Longest range a point cloud or an altimeter reading may hold, m; a longer one is a corrupt sample and counts as
no return."""
MAX_BARO_ALT_M = 1e5
"""Largest barometric altitude magnitude a reading may hold, m."""


@dataclass
class PointCloud:
    """A received point cloud, sensor frame.

    Attributes:
        dirs_s: (M, 3) unit ray directions of the pattern.
        ranges_m: (M,) measured ranges in m; NaN = invalid (no return, a NaN sample, or a range ≤ 0 or beyond
            :data:`MAX_RANGE_M`, which no terrain sensor returns).
    """

    dirs_s: np.ndarray
    ranges_m: np.ndarray

    def __post_init__(self):
        self.dirs_s = np.asarray(self.dirs_s, dtype=np.float64)
        r = np.asarray(self.ranges_m, dtype=np.float64).copy()
        if self.dirs_s.ndim != 2 or self.dirs_s.shape[1] != 3 or r.shape != (len(self.dirs_s),):
            raise FilterError(f"point cloud needs dirs (M, 3) and ranges (M,), got {self.dirs_s.shape} and {r.shape}")
        if len(r) == 0:
            raise FilterError("point cloud is empty")
        norm = np.linalg.norm(self.dirs_s, axis=1)
        if not np.all(np.abs(norm - 1.0) < 1e-6):
            raise FilterError("point cloud directions must be unit vectors")
        with np.errstate(invalid="ignore"):
            r[~((r > 0.0) & (r <= MAX_RANGE_M))] = np.nan
        self.ranges_m = r

    @classmethod
    def _of_pattern(cls, pattern: ScanPattern, ranges_m: np.ndarray) -> PointCloud:
        """A cloud of ``pattern``'s directions (normalised when the pattern was made: not checked again) and float64
        ranges (M,) owned by the cloud; the same invalid ranges as the checked constructor."""
        cloud = cls.__new__(cls)
        cloud.dirs_s = pattern.dirs_s
        with np.errstate(invalid="ignore"):
            ranges_m[~((ranges_m > 0.0) & (ranges_m <= MAX_RANGE_M))] = np.nan
        cloud.ranges_m = ranges_m
        return cloud

    @classmethod
    def from_points(cls, points_s) -> PointCloud:
        """From (M, 3) sensor-frame points ``c_j``; rows with a NaN (or at the origin) are invalid."""
        c = np.asarray(points_s, dtype=np.float64)
        if c.ndim != 2 or c.shape[1] != 3:
            raise FilterError(f"points must have shape (M, 3), got {c.shape}")
        r = np.linalg.norm(c, axis=1)
        ok = np.isfinite(r) & (r > 0)
        dirs = np.where(ok[:, None], c / np.where(ok, r, 1.0)[:, None], [0.0, 0.0, 1.0])
        return cls(dirs, np.where(ok, r, np.nan))

    @property
    def valid(self) -> np.ndarray:
        """(M,) bool: point has a return."""
        return np.isfinite(self.ranges_m)

    @property
    def points_s(self) -> np.ndarray:
        """(M, 3) points ``c_j = r_j d_j`` in m (NaN rows invalid)."""
        return self.ranges_m[:, None] * self.dirs_s


class PointCloudSensor:
    """Simulates the point-cloud sensor against the truth terrain.

    Args:
        pattern: The scan pattern (sensor = body frame).
        range_sigma_m: Range noise σ in m (default 0.5 m).
        max_range_m: Returns beyond this range are dropped (None: no limit).
        caster: Ray-cast backend for the truth (default exact heightfield DDA).
    """

    def __init__(self, pattern: ScanPattern, range_sigma_m: float = 0.5, max_range_m: float | None = None,
                 caster: RayCaster | None = None):
        if not (np.isfinite(range_sigma_m) and range_sigma_m >= 0):
            raise FilterError(f"range_sigma_m must be ≥ 0, got {range_sigma_m!r}")
        self.pattern = pattern
        self.range_sigma_m = float(range_sigma_m)
        self.max_range_m = max_range_m
        self.caster = caster or RayCaster("dda")
        self._cast = None  # (terrain, caster, device, pose buffers, ranges, recorded launch) of the last call

    def measure(self, terrain, pos_n, quat_nb, rng: np.random.Generator | None = None, device=None) -> PointCloud:
        """One scan from the true pose ``(pos_n (3,), quat_nb (4,))``; ``rng=None`` means no noise."""
        return self.measure_many(terrain, pos_n, quat_nb, [rng], device)[0]

    def measure_many(self, terrain, pos_n, quat_nb, rngs, device=None) -> list[PointCloud]:
        """Scans from one true pose with independent noise, one per generator in ``rngs`` (one ray cast)."""
        pos = np.asarray(pos_n, dtype=np.float64).reshape(3)
        if not np.isfinite(pos).all():
            raise FilterError(f"sensor position is not finite: {pos}")
        q = check_unit_quat(np.asarray(quat_nb).reshape(4), "sensor attitude")
        exact = self._exact_ranges(terrain, pos, q, wp.get_device(device))
        clouds = []
        for rng in rngs:
            ranges = exact.copy()
            if rng is not None and self.range_sigma_m > 0:
                ranges += rng.normal(0.0, self.range_sigma_m, exact.shape)
            if self.max_range_m is not None:
                ranges[ranges > self.max_range_m] = np.nan
            clouds.append(PointCloud._of_pattern(self.pattern, ranges))
        return clouds

    def _exact_ranges(self, terrain, pos: np.ndarray, quat: np.ndarray, device) -> np.ndarray:
        """(M,) float64 noiseless ranges from one pose: one recorded cast into buffers kept for the terrain and
        caster and device of the last call (a scan every 0.1 s of a run cost 0.2 ms of array making and
        launching)."""
        cast = self._cast
        if cast is not None and cast[0] is terrain and cast[1] is self.caster and cast[2] == device:
            pos_buf, quat_buf, out, launch = cast[3:]
            upload(pos_buf, pos[None])
            upload(quat_buf, quat[None])
            launch.launch()
        else:
            pos_buf = wp.array(pos[None].astype(np.float32), dtype=wp.vec3, device=device)
            quat_buf = wp.array(quat[None].astype(np.float32), dtype=wp.vec4, device=device)
            out = wp.empty((1, self.pattern.m), dtype=wp.float32, device=device)
            launch = raycast_pattern(terrain, pos_buf, quat_buf, self.pattern.device_dirs(device), self.caster,
                                     out=out, record=True)
            self._cast = (terrain, self.caster, device, pos_buf, quat_buf, out, launch)
        return out.numpy()[0].astype(np.float64)


@dataclass(frozen=True)
class AltimeterReading:
    """A radar-altimeter range with the barometric altitude used to predict it (m; NaN = no barometer)."""

    range_m: float
    baro_alt_m: float = float("nan")

    def __post_init__(self):
        try:
            r, baro = float(self.range_m), float(self.baro_alt_m)
        except (TypeError, ValueError):
            raise FilterError(f"altimeter reading needs numbers, got {self.range_m!r}, {self.baro_alt_m!r}") from None
        if abs(baro) > MAX_BARO_ALT_M:  # NaN (no barometer) passes
            raise FilterError(f"baro_alt_m = {baro!r} is not an altitude (|h| ≤ {MAX_BARO_ALT_M:g} m; NaN = none)")
        object.__setattr__(self, "range_m", r if 0.0 < r <= MAX_RANGE_M else float("nan"))
        object.__setattr__(self, "baro_alt_m", baro)

    @property
    def valid(self) -> bool:
        """The range is finite (the barometer is checked by the model that uses it)."""
        return bool(np.isfinite(self.range_m))


class RadarAltimeter:
    """Vertical distance to the terrain ``a = -p_z - h_true(p_x, p_y)`` plus noise (σ default 1 m)."""

    def __init__(self, sigma_m: float = 1.0):
        if not (np.isfinite(sigma_m) and sigma_m >= 0):
            raise FilterError(f"altimeter sigma_m must be ≥ 0, got {sigma_m!r}")
        self.sigma_m = float(sigma_m)

    def measure(self, terrain, pos_n, rng: np.random.Generator | None = None) -> float:
        """The range in m (NaN off the map or over nodata)."""
        p = np.asarray(pos_n, dtype=np.float64).reshape(3)
        a = float(-p[2] - terrain.height_at(p[0], p[1]))
        if rng is not None and self.sigma_m > 0 and np.isfinite(a):
            a += rng.normal(0.0, self.sigma_m)
        return a


class Barometer:
    """Barometric altitude ``-p_z`` plus white noise (σ default 1 m) and an optional constant bias (m)."""

    def __init__(self, sigma_m: float = 1.0, bias_m: float = 0.0):
        if not (np.isfinite(sigma_m) and sigma_m >= 0 and np.isfinite(bias_m)):
            raise FilterError(f"barometer needs sigma_m ≥ 0 and a finite bias, got {sigma_m!r}, {bias_m!r}")
        self.sigma_m = float(sigma_m)
        self.bias_m = float(bias_m)

    def measure(self, pos_n, rng: np.random.Generator | None = None) -> float:
        """Altitude in m."""
        alt = float(-np.asarray(pos_n, dtype=np.float64).reshape(3)[2]) + self.bias_m
        if rng is not None and self.sigma_m > 0:
            alt += rng.normal(0.0, self.sigma_m)
        return alt
