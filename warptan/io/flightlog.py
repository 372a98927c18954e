"""The warptan flight log: a recorded flight in one HDF5 file that ``warptan replay`` filters (format version 2).

Why HDF5 (h5py): a flight is a few long time series of different rates and shapes — IMU samples (K, 3), scans
(S, M) with their directions, altimeter and barometer readings — plus metadata. HDF5 holds them in one file as
named, typed, chunked arrays with units as attributes, is read natively by MATLAB (``h5read``), Python, Julia and C,
and needs no table flattening (Parquet would store a scan as M columns or a list column). The layout::

    /                    format = "warptan-flight-log", version = 2, name
    /frame               attrs kind = "geodetic": origin_lat_deg, origin_lon_deg (WGS84), origin_height_m (height of
                         the NED origin above the vertical datum), vertical_datum (its name; "" = not stated) — the
                         map frame tied to the Earth (:class:`~warptan.nav.geoframe.GeoFrame`); or kind = "dem-grid":
                         the frame is the grid of the DEM named in /dem and nothing else (a generated terrain)
    /imu                 t (K,) s; f_b (K, 3) m/s² specific force; w_b (K, 3) rad/s body rate — body frame FRD;
                         attrs rate_hz (nominal rate), grade (IMU grade name), t_end (end of the last sample's step)
    /scans   (optional)  t (S,) s; dirs_s (S, M, 3) unit directions, sensor frame FRD; ranges_m (S, M);
                         valid (S, M) bool; attrs range_sigma_m
    /altimeter (opt.)    t (A,) s; range_m (A,) (NaN = no return); attrs sigma_m
    /baro    (optional)  t (P,) s; alt_m (P,) barometric altitude above the DEM's datum (= -down); attrs sigma_m
    /truth   (optional)  t (T,) s; pos_n (T, 3) m, vel_n (T, 3) m/s (NED in the DEM's map frame); quat_nb (T, 4)
                         [w, x, y, z] body FRD to NED; accel_bias (T, 3), gyro_bias (T, 3) (optional)
    /initial             t, pos_n, vel_n, quat_nb, accel_bias, gyro_bias (the INS's initial nominal state);
                         sigma (15,): σ of its error [pos m (3), vel m/s (3), attitude rad (3), accel bias m/s² (3),
                         gyro bias rad/s (3)] — the filter's prior
    /mounting            quat_bs (4,) sensor to body; lever_b (3,) m, sensor origin in the body frame
    /dem                 attrs reference (path or spec of the DEM the flight is over), crs; posts (optional, 6
                         floats): north and east of the DEM's first post, its post spacings north and east (m, in
                         the map frame) and its rows and columns, when that DEM's grid is the frame's (a resampled
                         DEM, e.g. the package's tiles): replay over another cut of that DEM resamples it onto the
                         same posts
    /settings (optional) attrs json: the filter settings of the run that wrote the log (replay defaults)

Conventions: times in seconds on one clock. IMU sample k (``f_b[k]``, ``w_b[k]``) is held over its step
``[t[k], t[k+1])`` (the last one until ``t_end``): the zero-order hold warptan's own INS integrates. Map frame
(version 2, kind geodetic): north/east in metres of the transverse Mercator (WGS84, scale 1) centred on the frame's
origin — north is true north at the origin — and down = ``origin_height_m`` − height above the vertical datum
(:mod:`warptan.nav.geoframe`; ``warptan replay`` converts positions, velocities and attitudes into the frame of
whichever DEM covers the flight). Kind dem-grid, and every version 1 log: north/east in metres on the named DEM's grid,
down = −altitude above its datum (such a log flies only over its own DEM; version 1 is still read, with a warning when
replayed over another DEM). Point-cloud mounting: a point ``c_s = r d_s`` in the sensor frame is
``R(quat_bs) c_s + lever_b`` in the body frame; the altimeter's range is taken as vertical from the body origin.

:func:`read_log` validates the whole file and lists every problem it finds at once (:class:`LogError`);
:func:`write_log` validates before it writes and writes beside the target, then renames: a bad log writes nothing.
"""

from __future__ import annotations

import json
import os
import uuid
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from warptan.checks import FilterError, host_memory_available
from warptan.nav.geoframe import GeoFrame
from warptan.nav.imu import IMU_GRADES, imu_grade

FORMAT = "warptan-flight-log"
VERSION = 2
READABLE_VERSIONS = (1, 2)
FRAME_KINDS = ("geodetic", "dem-grid")
MAX_GAP_S = 1.0
"""Longest gap between consecutive IMU samples a log may have, s (a longer one is lost data)."""
UNIT_TOL = 1e-6


class LogError(FilterError):
    """A flight log that cannot be used; the message lists every problem found."""

    def __init__(self, source: str, problems: list[str]):
        self.source = source
        self.problems = list(problems)
        super().__init__(f"{source}: {len(problems)} problem(s): " + "; ".join(problems))


@dataclass
class FlightLog:
    """A recorded flight (see the module docstring for units and frames). Arrays are float64 NumPy arrays."""

    imu_t: np.ndarray
    imu_f: np.ndarray
    imu_w: np.ndarray
    imu_rate_hz: float
    imu_grade: str
    t_end: float
    init_t: float
    init_pos: np.ndarray
    init_vel: np.ndarray
    init_quat: np.ndarray
    init_sigma: np.ndarray
    init_accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    init_gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    scan_t: np.ndarray | None = None
    scan_dirs: np.ndarray | None = None
    scan_ranges: np.ndarray | None = None
    scan_valid: np.ndarray | None = None
    range_sigma_m: float = 0.5
    alt_t: np.ndarray | None = None
    alt_range: np.ndarray | None = None
    altimeter_sigma_m: float = 1.0
    baro_t: np.ndarray | None = None
    baro_alt: np.ndarray | None = None
    baro_sigma_m: float = 1.0
    truth_t: np.ndarray | None = None
    truth_pos: np.ndarray | None = None
    truth_vel: np.ndarray | None = None
    truth_quat: np.ndarray | None = None
    truth_accel_bias: np.ndarray | None = None
    truth_gyro_bias: np.ndarray | None = None
    mount_quat: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    mount_lever: np.ndarray = field(default_factory=lambda: np.zeros(3))
    dem_reference: str = ""
    dem_crs: str = ""
    dem_posts: np.ndarray | None = None
    """(6,) ``[n0, e0, dn, de, rows, cols]``: the first post (north, east) and spacings of the log's DEM in its map
    frame (m) and its size (written when that grid is the frame's; module docstring); None: not recorded. Unused
    without a geodetic frame."""
    settings: dict = field(default_factory=dict)
    name: str = "flight"
    frame: GeoFrame | None = None
    """The map frame on the Earth; None: the grid of the DEM named in ``dem_reference`` (kind dem-grid)."""
    version: int = VERSION
    """The format version the log was read from (1: the frame is its DEM's grid, no frame group)."""

    @property
    def has_truth(self) -> bool:
        return self.truth_t is not None

    @property
    def has_scans(self) -> bool:
        return self.scan_t is not None

    @property
    def has_altimeter(self) -> bool:
        return self.alt_t is not None

    @property
    def step_s(self) -> np.ndarray:
        """(K,) each IMU sample's step, s."""
        return np.diff(np.r_[self.imu_t, self.t_end])

    def problems(self) -> list[str]:
        """Every problem of the log (empty: usable)."""
        return _problems(self)

    def validate(self, source: str = "flight log") -> FlightLog:
        """Raise a :class:`LogError` listing every problem; return self when there is none."""
        found = self.problems()
        if found:
            raise LogError(source, found)
        return self


def _finite_rows(name: str, a: np.ndarray, problems: list[str]) -> None:
    if len(a) == 0:  # an empty stream is reported by its time array
        return
    bad = ~np.isfinite(a).reshape(len(a), -1).all(axis=1)
    if bad.any():
        problems.append(f"{name} has {int(bad.sum())} non-finite sample(s) (first at index {int(np.argmax(bad))})")


def _in_range(log: FlightLog, problems: list[str]) -> None:
    """IMU samples beyond the grade's measurement range (the filter refuses them): the first one named."""
    grade = imu_grade(log.imu_grade)
    bad = (np.abs(log.imu_f) > grade.accel_range).any(axis=1) | (np.abs(log.imu_w) > grade.gyro_range).any(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        problems.append(f"imu has {int(bad.sum())} sample(s) beyond the {grade.name} grade's range (|f| ≤ "
                        f"{grade.accel_range:g} m/s², |ω| ≤ {grade.gyro_range:g} rad/s per axis); first: sample {i} "
                        f"at t = {float(log.imu_t[i])!r} s, f_b = {log.imu_f[i].tolist()} m/s², w_b = "
                        f"{log.imu_w[i].tolist()} rad/s")


def _increasing(name: str, t: np.ndarray, problems: list[str]) -> bool:
    if t.ndim != 1 or len(t) == 0:
        problems.append(f"{name} must be a non-empty 1-D time array, got shape {t.shape}")
        return False
    if not np.isfinite(t).all():
        problems.append(f"{name} has non-finite times (first at index {int(np.argmax(~np.isfinite(t)))})")
        return False
    back = np.diff(t) <= 0
    if back.any():
        i = int(np.argmax(back))
        problems.append(f"{name} is not strictly increasing: t[{i + 1}] = {float(t[i + 1])!r} s after "
                        f"t[{i}] = {float(t[i])!r} s")
        return False
    return True


def _shape(name: str, a, shape: tuple, problems: list[str]) -> bool:
    if a is None:
        problems.append(f"{name} is missing")
        return False
    if a.shape != shape:
        problems.append(f"{name} has shape {a.shape}, expected {shape}")
        return False
    return True


def _unit_quats(name: str, q: np.ndarray, problems: list[str]) -> None:
    with np.errstate(invalid="ignore"):
        bad = ~(np.abs(np.linalg.norm(q.reshape(-1, 4), axis=1) - 1.0) < UNIT_TOL)
    if bad.any():
        problems.append(f"{name} has {int(bad.sum())} quaternion(s) that are not unit [w, x, y, z] "
                        f"(first at index {int(np.argmax(bad))})")


def _problems(log: FlightLog) -> list[str]:
    p: list[str] = []
    if log.frame is not None:
        p.extend(log.frame.problems())
    if log.dem_posts is not None:
        posts = np.asarray(log.dem_posts)
        if (posts.shape != (6,) or not np.isfinite(posts).all() or not (posts[2:4] > 0).all()
                or not (posts[4:] >= 2).all() or (posts[4:] != np.round(posts[4:])).any()):
            p.append(f"dem.posts must be 6 finite numbers [n0, e0, dn, de, rows, cols] with positive spacings and "
                     f"whole sizes ≥ 2, got {posts.tolist()}")
    if log.imu_grade not in IMU_GRADES:
        p.append(f"imu.grade {log.imu_grade!r} is not a grade warptan knows ({', '.join(IMU_GRADES)})")
    if not (np.isfinite(log.imu_rate_hz) and log.imu_rate_hz > 0):
        p.append(f"imu.rate_hz must be a positive number, got {log.imu_rate_hz!r}")
    ok_t = _increasing("imu.t", log.imu_t, p)
    k = len(log.imu_t)
    if _shape("imu.f_b", log.imu_f, (k, 3), p):
        _finite_rows("imu.f_b", log.imu_f, p)
    if _shape("imu.w_b", log.imu_w, (k, 3), p):
        _finite_rows("imu.w_b", log.imu_w, p)
    if log.imu_grade in IMU_GRADES and k and not any("imu.f_b" in x or "imu.w_b" in x for x in p):
        _in_range(log, p)
    if ok_t:
        if not (np.isfinite(log.t_end) and log.t_end > log.imu_t[-1]):
            p.append(f"imu.t_end = {log.t_end!r} s must be after the last sample (t = {float(log.imu_t[-1])!r} s)")
        else:
            steps = log.step_s
            median = float(np.median(steps))
            if np.isfinite(log.imu_rate_hz) and log.imu_rate_hz > 0 and abs(log.imu_rate_hz * median - 1.0) > 0.01:
                p.append(f"imu.rate_hz = {log.imu_rate_hz:g} Hz, but the samples are {1.0 / median:.6g} Hz apart (the "
                         "median step; a rate of 1e12 Hz over 100 Hz samples had been taken)")
            gap = steps > MAX_GAP_S
            if gap.any():
                i = int(np.argmax(gap))
                p.append(f"imu has a gap of {steps[i]:.3f} s after t = {float(log.imu_t[i])!r} s (sample {i}; at most "
                         f"{MAX_GAP_S:g} s: a longer gap is lost data)")
    for name in ("init_pos", "init_vel", "init_accel_bias", "init_gyro_bias", "mount_lever"):
        a = getattr(log, name)
        if _shape(_field(name), a, (3,), p) and not np.isfinite(a).all():
            p.append(f"{_field(name)} is not finite: {a.tolist()}")
    for name in ("init_quat", "mount_quat"):
        if _shape(_field(name), getattr(log, name), (4,), p):
            _unit_quats(_field(name), getattr(log, name), p)
    if _shape("initial.sigma", log.init_sigma, (15,), p) and not (
            np.isfinite(log.init_sigma).all() and (log.init_sigma >= 0).all() and (log.init_sigma[:3] > 0).all()):
        p.append(f"initial.sigma must be 15 finite σ ≥ 0 (position σ > 0), got {log.init_sigma.tolist()}")
    if ok_t and not (np.isfinite(log.init_t) and abs(log.init_t - log.imu_t[0]) <= UNIT_TOL * log.step_s.max()):
        p.append(f"initial.t = {log.init_t!r} s must be the time of the first IMU sample ({float(log.imu_t[0])!r} s)")
    if not (log.has_scans or log.has_altimeter):
        p.append("the log has neither scans nor altimeter readings: nothing to navigate with")
    if log.has_scans and _increasing("scans.t", log.scan_t, p):
        s = len(log.scan_t)
        m = log.scan_ranges.shape[1] if log.scan_ranges is not None and log.scan_ranges.ndim == 2 else -1
        if m < 1:
            p.append(f"scans.ranges_m must have shape (S, M), got "
                     f"{None if log.scan_ranges is None else log.scan_ranges.shape}")
        else:
            _shape("scans.ranges_m", log.scan_ranges, (s, m), p)
            if _shape("scans.valid", log.scan_valid, (s, m), p) and _shape("scans.dirs_s", log.scan_dirs,
                                                                            (s, m, 3), p):
                d = log.scan_dirs[log.scan_valid]
                with np.errstate(invalid="ignore"):
                    bad = ~(np.abs(np.linalg.norm(d, axis=1) - 1.0) < UNIT_TOL)
                if bad.any():
                    p.append(f"scans.dirs_s has {int(bad.sum())} valid direction(s) that are not unit vectors")
                r = log.scan_ranges[log.scan_valid]
                with np.errstate(invalid="ignore"):
                    bad_r = ~((r > 0) & np.isfinite(r))
                if bad_r.any():
                    p.append(f"scans.ranges_m has {int(bad_r.sum())} point(s) marked valid with a range that is not a "
                             "positive number (NaN sensor samples must be marked invalid)")
    if log.has_altimeter and _increasing("altimeter.t", log.alt_t, p):
        _shape("altimeter.range_m", log.alt_range, log.alt_t.shape, p)
    if log.baro_t is not None and _increasing("baro.t", log.baro_t, p):
        if _shape("baro.alt_m", log.baro_alt, log.baro_t.shape, p):
            _finite_rows("baro.alt_m", log.baro_alt, p)
    if log.has_truth and _increasing("truth.t", log.truth_t, p):
        n = len(log.truth_t)
        for name, width in (("truth_pos", 3), ("truth_vel", 3), ("truth_quat", 4)):
            if _shape(_field(name), getattr(log, name), (n, width), p):
                _finite_rows(_field(name), getattr(log, name), p)
        if log.truth_quat is not None and log.truth_quat.shape == (n, 4):
            _unit_quats("truth.quat_nb", log.truth_quat, p)
        for name in ("truth_accel_bias", "truth_gyro_bias"):
            if getattr(log, name) is not None:
                _shape(_field(name), getattr(log, name), (n, 3), p)
    for name in ("range_sigma_m", "altimeter_sigma_m", "baro_sigma_m"):
        v = getattr(log, name)
        if not (np.isfinite(v) and v >= 0):
            p.append(f"{_field(name)} must be a number ≥ 0, got {v!r}")
    return p


_FIELDS = {"init_pos": "initial.pos_n", "init_vel": "initial.vel_n", "init_quat": "initial.quat_nb",
           "init_accel_bias": "initial.accel_bias", "init_gyro_bias": "initial.gyro_bias",
           "mount_quat": "mounting.quat_bs", "mount_lever": "mounting.lever_b", "truth_pos": "truth.pos_n",
           "truth_vel": "truth.vel_n", "truth_quat": "truth.quat_nb", "truth_accel_bias": "truth.accel_bias",
           "truth_gyro_bias": "truth.gyro_bias", "range_sigma_m": "scans.range_sigma_m",
           "altimeter_sigma_m": "altimeter.sigma_m", "baro_sigma_m": "baro.sigma_m"}


def _field(name: str) -> str:
    """The log's name of a FlightLog attribute (group.dataset), for messages."""
    return _FIELDS.get(name, name)


# ---------------------------------------------------------------------- file
_LAYOUT = {  # group: [(dataset, attribute)]
    "imu": [("t", "imu_t"), ("f_b", "imu_f"), ("w_b", "imu_w")],
    "scans": [("t", "scan_t"), ("dirs_s", "scan_dirs"), ("ranges_m", "scan_ranges"), ("valid", "scan_valid")],
    "altimeter": [("t", "alt_t"), ("range_m", "alt_range")],
    "baro": [("t", "baro_t"), ("alt_m", "baro_alt")],
    "truth": [("t", "truth_t"), ("pos_n", "truth_pos"), ("vel_n", "truth_vel"), ("quat_nb", "truth_quat"),
              ("accel_bias", "truth_accel_bias"), ("gyro_bias", "truth_gyro_bias")],
    "initial": [("pos_n", "init_pos"), ("vel_n", "init_vel"), ("quat_nb", "init_quat"), ("sigma", "init_sigma"),
                ("accel_bias", "init_accel_bias"), ("gyro_bias", "init_gyro_bias")],
    "mounting": [("quat_bs", "mount_quat"), ("lever_b", "mount_lever")],
}
_SCALARS = {  # (group, attribute) -> FlightLog attribute
    ("imu", "rate_hz"): "imu_rate_hz", ("imu", "grade"): "imu_grade", ("imu", "t_end"): "t_end",
    ("initial", "t"): "init_t", ("scans", "range_sigma_m"): "range_sigma_m",
    ("altimeter", "sigma_m"): "altimeter_sigma_m", ("baro", "sigma_m"): "baro_sigma_m",
    ("dem", "reference"): "dem_reference", ("dem", "crs"): "dem_crs",
}
_UNITS = {"t": "s", "f_b": "m/s^2 (specific force, body FRD)", "w_b": "rad/s (body FRD)",
          "dirs_s": "unit vector, sensor FRD", "ranges_m": "m", "range_m": "m", "alt_m": "m above datum",
          "pos_n": "m, NED map frame", "vel_n": "m/s, NED", "quat_nb": "[w, x, y, z], body FRD to NED",
          "quat_bs": "[w, x, y, z], sensor to body", "lever_b": "m, body FRD", "accel_bias": "m/s^2",
          "gyro_bias": "rad/s", "sigma": "pos m (3), vel m/s (3), att rad (3), accel bias m/s^2 (3), gyro bias "
                                         "rad/s (3)", "valid": "bool"}
_REQUIRED = ("imu", "initial", "mounting")
_FRAME_KEYS = ("origin_lat_deg", "origin_lon_deg", "origin_height_m", "vertical_datum")


def _read_frame(attrs, source: str) -> GeoFrame | None:
    """The /frame group's frame (None for kind dem-grid); a :class:`LogError` names what is missing or wrong."""
    def text(v):
        return v.decode() if isinstance(v, bytes) else str(v)

    kind = text(attrs.get("kind", ""))
    if kind not in FRAME_KINDS:
        raise LogError(source, [f"frame.kind = {kind!r} is not one of {', '.join(FRAME_KINDS)}"])
    if kind == "dem-grid":
        return None
    missing = [f"frame.{k} is missing" for k in _FRAME_KEYS if k not in attrs]
    if missing:
        raise LogError(source, missing)
    values = []
    for key in _FRAME_KEYS[:3]:
        try:
            values.append(float(attrs[key]))
        except (TypeError, ValueError):
            raise LogError(source, [f"frame.{key} = {attrs[key]!r} is not a number"]) from None
    return GeoFrame(*values, text(attrs["vertical_datum"]))


def write_log(log: FlightLog, path: str | os.PathLike, exclusive: bool = False) -> Path:
    """Write ``log`` to ``path`` (HDF5), validated first. The file is built in memory and then written beside the
    target and renamed into place: a write that fails (a full disk, a file size limit) is an ``OSError`` naming
    ``path``, with nothing left there and a previous file of that name as it was. (Written by the HDF5 library
    itself, a failed write left it in a state whose clean-up crashed the process: dozens of ignored exceptions, then
    a segmentation fault.) ``exclusive``: a file that exists at ``path`` when the new one is complete is never
    replaced (``FileExistsError``): two writers of one name, the loser's work is dropped, the winner's kept."""
    import io

    import h5py

    path = Path(path)
    log.validate(f"flight log {path}")
    tmp = path.with_name(f".{path.name}.partial-{uuid.uuid4().hex[:8]}")  # (one per writer: two had shared one)
    buffer = io.BytesIO()
    with h5py.File(buffer, "w") as f:
        _write_hdf5(log, f)
    try:
        with open(tmp, "wb") as out:
            out.write(buffer.getbuffer())
        if exclusive:
            os.link(tmp, path)  # (fails if the name exists: never replaces)
        else:
            os.replace(tmp, path)
    except FileExistsError:
        raise
    except OSError as err:
        raise OSError(err.errno, err.strerror or str(err), str(path)) from None
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def _write_hdf5(log: FlightLog, f) -> None:
    """The log's groups, datasets and attributes into the open HDF5 file ``f``."""
    f.attrs["format"] = FORMAT
    f.attrs["version"] = VERSION
    f.attrs["name"] = log.name
    for group, items in _LAYOUT.items():
        values = {ds: getattr(log, attr) for ds, attr in items}
        if all(v is None for v in values.values()):
            continue
        g = f.create_group(group)
        for ds, value in values.items():
            if value is not None:
                d = g.create_dataset(ds, data=np.asarray(value), compression="gzip" if np.size(value) > 4096
                                     else None)
                d.attrs["units"] = _UNITS.get(ds, "")
    for (group, key), attr in _SCALARS.items():
        if group in f or group == "dem":
            g = f.require_group(group)
            g.attrs[key] = getattr(log, attr)
    frame = f.create_group("frame")
    frame.attrs["kind"] = "dem-grid" if log.frame is None else "geodetic"
    if log.frame is not None:
        for key in _FRAME_KEYS:
            frame.attrs[key] = getattr(log.frame, key)
    if log.dem_posts is not None:
        f["dem"].attrs["posts"] = np.asarray(log.dem_posts, dtype=np.float64)
    if log.settings:
        f.create_group("settings").attrs["json"] = json.dumps(log.settings, sort_keys=True)


def read_log(path: str | os.PathLike) -> FlightLog:
    """Read and validate a flight log; a :class:`LogError` lists every problem (a file that is not a warptan log
    at all: one problem saying so)."""
    import h5py

    path = Path(path)
    source = f"flight log {path}"
    if not path.is_file():
        raise LogError(source, ["no such file"])
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise LogError(source, [f"not an HDF5 file ({err})"]) from None
    with f:
        if f.attrs.get("format") != FORMAT:
            raise LogError(source, [f"not a warptan flight log (attribute format = {f.attrs.get('format')!r}, "
                                    f"expected {FORMAT!r})"])
        version = int(f.attrs.get("version", -1))
        if version not in READABLE_VERSIONS:
            raise LogError(source, [f"format version {version} is not one this warptan reads "
                                    f"({', '.join(map(str, READABLE_VERSIONS))})"])
        problems = [f"group /{g} is missing" for g in _REQUIRED + (("frame",) if version >= 2 else ()) if g not in f]
        if problems:
            raise LogError(source, problems)
        need = sum(8.0 * f[g][ds].size for g, items in _LAYOUT.items() if g in f for ds, _ in items if ds in f[g])
        have = host_memory_available()
        if need > 0.5 * have:  # (from the datasets' shapes: a 175 kB log declaring 400 M samples was read whole)
            raise LogError(source, [f"its datasets declare {need / 1e9:.3g} GB of samples but {have / 1e9:.3g} GB of "
                                    "memory is available; cut the log into shorter flights"])
        kw: dict = {"name": str(f.attrs.get("name", path.stem)), "version": version}
        if version >= 2:
            kw["frame"] = _read_frame(f["frame"].attrs, source)
        for group, items in _LAYOUT.items():
            if group not in f:
                continue
            for ds, attr in items:
                if ds in f[group]:
                    kw[attr] = np.asarray(f[group][ds][()])
                    if ds != "valid":
                        kw[attr] = kw[attr].astype(np.float64)
                    else:
                        kw[attr] = kw[attr].astype(bool)
        for (group, key), attr in _SCALARS.items():
            if group in f and key in f[group].attrs:
                value = f[group].attrs[key]
                kw[attr] = value.decode() if isinstance(value, bytes) else (str(value) if isinstance(value, str)
                                                                          else float(value))
        if "settings" in f:
            kw["settings"] = json.loads(f["settings"].attrs["json"])
        if "dem" in f and "posts" in f["dem"].attrs:
            kw["dem_posts"] = np.asarray(f["dem"].attrs["posts"], dtype=np.float64).reshape(-1)
    missing = [name for name, attr in (("imu.t", "imu_t"), ("imu.f_b", "imu_f"), ("imu.w_b", "imu_w"),
                                       ("imu.rate_hz", "imu_rate_hz"), ("imu.grade", "imu_grade"),
                                       ("imu.t_end", "t_end"), ("initial.t", "init_t"), ("initial.pos_n", "init_pos"),
                                       ("initial.vel_n", "init_vel"), ("initial.quat_nb", "init_quat"),
                                       ("initial.sigma", "init_sigma")) if attr not in kw]
    if missing:
        raise LogError(source, [f"{name} is missing" for name in missing])
    if "scan_t" in kw and "scan_ranges" in kw:
        kw.setdefault("scan_valid", np.isfinite(kw["scan_ranges"]))
        kw["scan_ranges"] = np.where(kw["scan_valid"], kw["scan_ranges"], np.nan)
    return FlightLog(**kw).validate(source)


def sample_at(t_src: np.ndarray, values: np.ndarray, t: np.ndarray, unit: bool = False) -> np.ndarray:
    """``values`` (T, n) at times ``t``: exact at a recorded time, else linear (normalised when ``unit``)."""
    i = np.clip(np.searchsorted(t_src, t), 1, len(t_src) - 1)
    t0, t1 = t_src[i - 1], t_src[i]
    frac = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)[:, None]
    out = values[i - 1] + frac * (values[i] - values[i - 1])
    if unit:
        out = out / np.linalg.norm(out, axis=1, keepdims=True)
    exact = np.searchsorted(t_src, t)
    hit = (exact < len(t_src)) & (t_src[np.minimum(exact, len(t_src) - 1)] == t)
    out[hit] = values[exact[hit]]
    outside = (t < t_src[0]) | (t > t_src[-1])
    out[outside] = np.nan
    return out
