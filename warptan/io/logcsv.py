"""Bring your own flight: a flight log from tables of what a vehicle records (GPS latitude/longitude/height, IMU
samples, point clouds or altimeter ranges, barometer), and the same tables written from a log.

:func:`from_geodetic` is the API (arrays in, a :class:`~warptan.io.flightlog.FlightLog` out); :func:`read_tables`
reads a layout file (TOML) naming CSV files, their columns and units, and ``warptan log import LAYOUT.toml --out
F.h5`` is its command; :func:`write_tables` (``warptan log export F.h5 --out DIR``) writes a log as such tables and
layout (a worked example to start from). The layout::

    name = "my_flight"             # optional (default: the layout file's name)
    dem = "my_dem.tif"             # optional: the DEM the flight is over (the log's dem.reference)
    vertical_datum = "EGM96"       # the datum the heights are above ("" = not stated; the DEM's must be the same)
    imu_grade = "navigation"       # a grade warptan knows (warptan.nav.imu.IMU_GRADES)
    initial_sigma = [...]          # optional: 15 σ of the initial error (default: the scenarios' prior for the grade)
    range_sigma_m = 0.5            # optional sensor σ (also altimeter_sigma_m, baro_sigma_m)
    mount_quat_bs = [1, 0, 0, 0]   # optional: sensor to body [w, x, y, z], FRD; mount_lever_b = [x, y, z] m
    settings_json = "{...}"        # optional: filter settings (a log's /settings), as warptan log export writes
    [imu]        file = "imu.csv", columns t fx fy fz wx wy wz (specific force and body rate, body FRD)
    [gps]        file = "gps.csv", columns t lat lon height roll pitch yaw, optional vn ve vd (true-north NED)
    [scans]      file = "scans.csv", one row per point: t x y z (sensor frame FRD; an empty or NaN coordinate is
                 no return), the rows of one scan share its t and every scan has the same number of rows
    [altimeter]  file = "altimeter.csv", columns t range
    [baro]       file = "baro.csv", columns t alt (height above the datum)
    [initial]    optional: the vehicle's own navigation solution at the first IMU sample (lat_deg, lon_deg, height_m,
                 roll_deg, pitch_deg, yaw_deg, vel_ned = [n, e, d] m/s true north; accel_bias, gyro_bias SI); default
                 the GPS there

Every table may rename its columns (``columns = {t = "time_ns", lat = "Latitude"}``) and state units
(``units = {t = "ns", lat = "deg", fx = "g"}``, one per column key; defaults: s, deg, m, m/s², rad/s, m/s). Files are
relative to the layout file. The GPS is the truth; the initial nominal state is the GPS (and its attitude) at the
first IMU sample, and the log's frame is the tangent frame at the first GPS fix (height 0 on the datum).
"""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import numpy as np

from warptan.filter.prior import InitialErrors, prior_sigma
from warptan.io.flightlog import FlightLog, LogError
from warptan.nav.frames import euler_to_quat, quat_to_euler
from warptan.nav.geoframe import GeoFrame, turn_vectors
from warptan.nav.imu import IMU_GRADES

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

UNITS = {
    "time": {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9},
    "angle": {"deg": math.pi / 180.0, "rad": 1.0},
    "length": {"m": 1.0, "ft": 0.3048},
    "accel": {"m/s^2": 1.0, "m/s2": 1.0, "g": 9.80665},
    "rate": {"rad/s": 1.0, "deg/s": math.pi / 180.0},
    "speed": {"m/s": 1.0, "kn": 1852.0 / 3600.0, "ft/s": 0.3048},
}
"""Units a layout may state, per quantity: factor to SI (angles: to radians, then degrees where warptan keeps
degrees)."""

TABLES = {  # table: {required column key: quantity}; OPTIONAL_COLUMNS holds the optional ones
    "imu": {"t": "time", "fx": "accel", "fy": "accel", "fz": "accel", "wx": "rate", "wy": "rate", "wz": "rate"},
    "gps": {"t": "time", "lat": "angle", "lon": "angle", "height": "length", "roll": "angle", "pitch": "angle",
            "yaw": "angle"},
    "scans": {"t": "time", "x": "length", "y": "length", "z": "length"},
    "altimeter": {"t": "time", "range": "length"},
    "baro": {"t": "time", "alt": "length"},
}
OPTIONAL_COLUMNS = {"gps": {"vn": "speed", "ve": "speed", "vd": "speed"}}
LAYOUT_KEYS = {"name", "dem", "vertical_datum", "imu_grade", "imu_rate_hz", "initial_sigma", "range_sigma_m",
               "altimeter_sigma_m", "baro_sigma_m", "mount_quat_bs", "mount_lever_b", "initial", "settings_json",
               *TABLES}
INITIAL_KEYS = ("lat_deg", "lon_deg", "height_m", "roll_deg", "pitch_deg", "yaw_deg", "vel_ned", "accel_bias",
                "gyro_bias")


# ---------------------------------------------------------------------- API
def from_geodetic(*, imu_t, imu_f, imu_w, imu_grade: str, gps_t, lat_deg, lon_deg, height_m, roll_rad, pitch_rad,
                  yaw_rad, vel_ned=None, imu_rate_hz: float | None = None, t_end: float | None = None,
                  init_sigma=None, scan_t=None, scan_points_s=None, alt_t=None, alt_range=None,
                  baro_t=None, baro_alt=None, range_sigma_m: float = 0.5, altimeter_sigma_m: float = 1.0,
                  baro_sigma_m: float = 1.0, mount_quat=(1.0, 0.0, 0.0, 0.0), mount_lever=(0.0, 0.0, 0.0),
                  vertical_datum: str = "", frame: GeoFrame | None = None, dem_reference: str = "",
                  initial: dict | None = None, settings: dict | None = None, name: str = "flight") -> FlightLog:
    """A flight log from geodetic truth (GPS latitude/longitude in degrees, height in m above ``vertical_datum``,
    attitude as roll/pitch/yaw in rad about true north, velocity in true-north NED m/s or None: differentiated from
    the positions), IMU samples (body FRD), and point clouds ``scan_points_s`` (S, M, 3; sensor FRD, NaN = no return)
    and/or altimeter ranges, barometric heights. The frame is ``frame`` or the tangent frame at the first fix;
    true-north vectors and headings are turned into its axes at each fix (its north is true north only at its
    origin). The initial nominal state is ``initial`` (keys lat_deg, lon_deg, height_m, roll_rad, pitch_rad, yaw_rad,
    vel_ned, optional accel_bias, gyro_bias: the vehicle's own navigation solution at the first IMU sample), else the
    truth there. Raises :class:`LogError` listing every problem (latitudes outside ±90°, times that go backwards, …)."""
    source = f"flight {name}"
    gps_t, lat, lon, h = (np.asarray(v, dtype=np.float64).reshape(-1) for v in (gps_t, lat_deg, lon_deg, height_m))
    problems = []
    with np.errstate(invalid="ignore"):
        bad_lat = ~(np.abs(lat) <= 90.0)
        bad_lon = ~(np.abs(lon) <= 360.0)
    if bad_lat.any():
        i = int(np.argmax(bad_lat))
        problems.append(f"gps latitude must be within ±90°: {int(bad_lat.sum())} fix(es), first at index {i} "
                        f"({lat[i]!r}°)")
    if bad_lon.any():
        i = int(np.argmax(bad_lon))
        problems.append(f"gps longitude must be a finite angle within ±360°: {int(bad_lon.sum())} fix(es), first at "
                        f"index {i} ({lon[i]!r}°)")
    if len(gps_t) < 2:
        problems.append(f"gps needs at least 2 fixes, got {len(gps_t)}")
    if frame is None and not problems:
        frame = GeoFrame(float(lat[0]), float(lon[0]), 0.0, vertical_datum)
    if frame is not None:
        problems += frame.problems()
    if problems:
        raise LogError(source, problems)
    n, e = frame.latlon_to_ne(lat, lon)
    pos = np.column_stack([n, e, frame.origin_height_m - h])
    turn = _north_turn(frame, lat, lon)
    euler = np.column_stack([np.asarray(v, dtype=np.float64).reshape(-1) for v in (roll_rad, pitch_rad, yaw_rad)])
    quat = euler_to_quat(euler[:, 0], euler[:, 1], euler[:, 2] + turn)
    if vel_ned is None:
        vel = np.gradient(pos, gps_t, axis=0) if np.all(np.diff(gps_t) > 0) else np.full_like(pos, np.nan)
    else:
        vel = turn_vectors(turn, np.asarray(vel_ned, dtype=np.float64).reshape(-1, 3))
    imu_t = np.asarray(imu_t, dtype=np.float64).reshape(-1)
    steps = np.diff(imu_t)
    rate = float(imu_rate_hz) if imu_rate_hz else (1.0 / float(np.median(steps)) if len(steps) else math.nan)
    kw: dict = {}
    if scan_t is not None:
        pts = np.asarray(scan_points_s, dtype=np.float64)
        r = np.linalg.norm(pts, axis=2)
        valid = np.isfinite(r) & (r > 0)
        kw.update(scan_t=np.asarray(scan_t, dtype=np.float64), scan_ranges=np.where(valid, r, np.nan),
                  scan_dirs=np.where(valid[..., None], pts / np.where(valid, r, 1.0)[..., None], np.nan),
                  scan_valid=valid, range_sigma_m=float(range_sigma_m))
    if alt_t is not None:
        kw.update(alt_t=np.asarray(alt_t, dtype=np.float64), alt_range=np.asarray(alt_range, dtype=np.float64),
                  altimeter_sigma_m=float(altimeter_sigma_m))
    if baro_t is not None:
        kw.update(baro_t=np.asarray(baro_t, dtype=np.float64), baro_alt=np.asarray(baro_alt, dtype=np.float64),
                  baro_sigma_m=float(baro_sigma_m))
    from warptan.io.flightlog import sample_at

    t0 = imu_t[:1]
    if len(imu_t) and not (gps_t[0] <= t0[0] <= gps_t[-1]) and initial is None:
        raise LogError(source, [f"the first IMU sample (t = {t0[0]!r} s) is outside the GPS's time span "
                                f"({gps_t[0]!r} … {gps_t[-1]!r} s): no initial state"])
    if initial is None:
        init = {"init_pos": sample_at(gps_t, pos, t0)[0], "init_vel": sample_at(gps_t, vel, t0)[0],
                "init_quat": sample_at(gps_t, quat, t0, unit=True)[0]}
    else:
        i = initial
        la, lo = np.array([float(i["lat_deg"])]), np.array([float(i["lon_deg"])])
        n0, e0 = frame.latlon_to_ne(la, lo)
        t = _north_turn(frame, la, lo)[0]
        init = {"init_pos": np.array([n0[0], e0[0], frame.origin_height_m - float(i["height_m"])]),
                "init_vel": turn_vectors(t, np.asarray(i["vel_ned"], dtype=np.float64)),
                "init_quat": euler_to_quat(float(i["roll_rad"]), float(i["pitch_rad"]), float(i["yaw_rad"]) + t),
                "init_accel_bias": np.asarray(i.get("accel_bias", np.zeros(3)), dtype=np.float64),
                "init_gyro_bias": np.asarray(i.get("gyro_bias", np.zeros(3)), dtype=np.float64)}
    log = FlightLog(
        imu_t=imu_t, imu_f=np.asarray(imu_f, dtype=np.float64), imu_w=np.asarray(imu_w, dtype=np.float64),
        imu_rate_hz=rate, imu_grade=str(imu_grade),
        t_end=float(t_end) if t_end is not None else float(imu_t[-1] + 1.0 / rate) if len(imu_t) else math.nan,
        init_t=float(imu_t[0]) if len(imu_t) else math.nan, **init,
        init_sigma=_initial_sigma(init_sigma, imu_grade), truth_t=gps_t, truth_pos=pos, truth_vel=vel,
        truth_quat=quat, mount_quat=np.asarray(mount_quat, dtype=np.float64),
        mount_lever=np.asarray(mount_lever, dtype=np.float64), dem_reference=dem_reference, frame=frame, name=name,
        settings=dict(settings or {}), **kw)
    return log.validate(source)


def _initial_sigma(init_sigma, grade: str) -> np.ndarray:
    """``init_sigma`` as floats, or (None) the scenarios' prior (:class:`~warptan.filter.prior.InitialErrors`:
    100/100/20 m, 0.5 m/s, 0.1/0.1/0.5°) with the grade's turn-on biases (NaN for a grade warptan does not know: the
    log's validation names the grade)."""
    if init_sigma is not None:
        return np.asarray(init_sigma, dtype=np.float64)
    if grade not in IMU_GRADES:
        return np.full(15, np.nan)
    return prior_sigma(InitialErrors(), IMU_GRADES[grade])


def _north_turn(frame, lat, lon) -> np.ndarray:
    """(K,) angle (rad, about down) from true north to the frame's north axis at each fix: a true-north heading ψ
    is ψ + this in the frame."""
    n0, e0 = frame.latlon_to_ne(lat, lon)
    n1, e1 = frame.latlon_to_ne(lat + 1e-5, lon)
    return np.arctan2(e1 - e0, n1 - n0)


# ---------------------------------------------------------------------- tables
def _read_csv(path: Path, table: str, spec: dict, problems: list[str]) -> dict | None:
    """The table's columns in SI units (angles in rad), keyed by column key; None after recording problems."""
    keys = {**TABLES[table], **OPTIONAL_COLUMNS.get(table, {})}
    if not isinstance(spec, dict):
        problems.append(f"[{table}] must be a table (file, columns, units), got {spec!r}")
        return None
    strange = sorted(set(spec) - {"file", "columns", "units"})
    if strange:  # (a misspelt "unit =" had been ignored: the default unit read instead)
        problems.append(f"[{table}] unknown key(s) {', '.join(strange)} (keys: file, columns, units)")
    names = spec.get("columns", {})
    units = spec.get("units", {})
    for what, given in (("column", names), ("unit", units)):
        if not isinstance(given, dict):
            problems.append(f"[{table}] {what}s must be a table of key = name, got {given!r}")
            return None
        unknown = sorted(set(given) - set(keys))
        if unknown:
            problems.append(f"[{table}] {what}s name unknown key(s) {', '.join(unknown)} (keys: {', '.join(keys)})")
    factors = {}
    for key, quantity in keys.items():
        unit = units.get(key, next(iter(UNITS[quantity])))
        if unit not in UNITS[quantity]:
            problems.append(f"[{table}] unit {unit!r} of {key} does not parse as a {quantity} unit "
                            f"({', '.join(UNITS[quantity])})")
        else:
            factors[key] = UNITS[quantity][unit]
    file = spec.get("file")
    if not isinstance(file, str) or not file:
        problems.append(f"[{table}] file is missing")
        return None
    path = path.parent / file
    try:
        with open(path, newline="", encoding="utf-8-sig") as fh:  # (a spreadsheet's byte-order mark: not a column)
            rows = list(csv.reader(fh))
    except OSError as err:
        problems.append(f"[{table}] {path}: {err.strerror or err}")
        return None
    except (UnicodeDecodeError, csv.Error) as err:
        problems.append(f"[{table}] {path}: not a UTF-8 CSV table ({err})")
        return None
    if not rows:
        problems.append(f"[{table}] {path}: empty file (no header)")
        return None
    header = [h.strip() for h in rows[0]]
    out = {}
    missing = []
    for key in keys:
        col = names.get(key, key)
        if col not in header:
            if key in TABLES[table]:
                missing.append(f"{col!r}" + (f" (for {key})" if col != key else ""))
            continue
        j = header.index(col)
        values = np.full(len(rows) - 1, np.nan)
        for i, row in enumerate(rows[1:]):
            text = row[j].strip() if j < len(row) else ""
            if text:
                try:
                    values[i] = float(text)
                except ValueError:
                    problems.append(f"[{table}] {path} row {i + 2}, column {col!r}: {text!r} is not a number")
                    return None
        out[key] = values * factors.get(key, 1.0)
    if missing:
        problems.append(f"[{table}] {path}: missing column(s) {', '.join(missing)} (the file has: "
                        f"{', '.join(header)})")
        return None
    t = out["t"]
    back = np.diff(t) < 0 if table == "scans" else np.diff(t) <= 0
    if back.any():
        i = int(np.argmax(back))
        problems.append(f"[{table}] {path}: times go backwards at row {i + 3} (t = {t[i + 1]!r} s after {t[i]!r} s)")
        return None
    return out


def read_tables(layout: str | os.PathLike) -> FlightLog:
    """A flight log from a layout file (module docstring); a :class:`LogError` lists every problem found."""
    path = Path(layout)
    source = f"layout {path}"
    try:
        spec = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        why = err.strerror if isinstance(err, OSError) and err.strerror else err  # (no raw "[Errno 2]")
        raise LogError(source, [f"does not load: {why}"]) from None
    problems = [f"unknown key {k!r} (known: {', '.join(sorted(LAYOUT_KEYS))})" for k in sorted(set(spec) - LAYOUT_KEYS)]
    for table in ("imu", "gps"):
        if table not in spec:
            problems.append(f"[{table}] table is missing")
    if "scans" not in spec and "altimeter" not in spec:
        problems.append("neither [scans] nor [altimeter]: nothing to navigate with")
    vectors = [("", spec, "mount_quat_bs", 4), ("", spec, "mount_lever_b", 3), ("", spec, "initial_sigma", 15)]
    if isinstance(spec.get("initial"), dict):
        vectors += [("[initial] ", spec["initial"], k, 3) for k in ("vel_ned", "accel_bias", "gyro_bias")]
    for where, table, key, size in vectors:  # ("cannot reshape array of size 2 into shape (3)" named nothing)
        value = table.get(key)
        if value is not None and not (isinstance(value, list) and len(value) == size and all(map(_number, value))):
            problems.append(f"{where}{key} = {value!r} must be a list of {size} finite numbers")
    if problems:
        raise LogError(source, problems)
    data = {t: _read_csv(path, t, spec[t], problems) for t in TABLES if t in spec}
    if problems:
        raise LogError(source, problems)
    imu, gps = data["imu"], data["gps"]
    problems += _check_streams(spec, data)
    if problems:
        raise LogError(source, problems)
    kw: dict = {}
    if "scans" in data:
        sc = data["scans"]
        times, counts = np.unique(sc["t"], return_counts=True)
        if len(set(counts.tolist())) > 1:
            raise LogError(source, [f"[scans] every scan must have the same number of rows (points); got "
                                    f"{sorted(set(counts.tolist()))}"])
        pts = np.column_stack([sc["x"], sc["y"], sc["z"]])[np.argsort(sc["t"], kind="stable")]
        kw.update(scan_t=times, scan_points_s=pts.reshape(len(times), int(counts[0]), 3))
    if "altimeter" in data:
        kw.update(alt_t=data["altimeter"]["t"], alt_range=data["altimeter"]["range"])
    if "baro" in data:
        kw.update(baro_t=data["baro"]["t"], baro_alt=data["baro"]["alt"])
    vel = (np.column_stack([gps["vn"], gps["ve"], gps["vd"]]) if all(k in gps for k in ("vn", "ve", "vd"))
           else None)
    try:
        settings = json.loads(spec.get("settings_json") or "{}")
    except (json.JSONDecodeError, TypeError) as err:
        raise LogError(source, [f"settings_json does not parse as JSON ({err})"]) from None
    if not isinstance(settings, dict):
        raise LogError(source, [f"settings_json must be a JSON object (the run's settings), got {settings!r}"])
    for key in ("range_sigma_m", "altimeter_sigma_m", "baro_sigma_m", "imu_rate_hz"):
        if key in spec:
            kw[key] = spec[key]
    if "initial" in spec:
        i = spec["initial"]
        missing = [k for k in INITIAL_KEYS[:7] if k not in i]
        unknown = sorted(set(i) - set(INITIAL_KEYS))
        if missing or unknown:
            keys = ", ".join(INITIAL_KEYS)
            raise LogError(source, [f"[initial] misses {', '.join(missing)}" if missing else
                                    f"[initial] has unknown key(s) {', '.join(unknown)} (keys: {keys})"])
        bad = [f"[initial] {k} = {i[k]!r} is not a number" for k in INITIAL_KEYS[:6] if not _number(i[k])]
        if bad:
            raise LogError(source, bad)
        far = _distance_km(float(i["lat_deg"]), float(i["lon_deg"]), float(np.degrees(gps["lat"][0])),
                           float(np.degrees(gps["lon"][0])))
        if far > 10.0:
            raise LogError(source, [f"[initial] is {far:.0f} km from the first GPS fix (lat {i['lat_deg']}°, lon "
                                    f"{i['lon_deg']}° against {np.degrees(gps['lat'][0]):.6f}°, "
                                    f"{np.degrees(gps['lon'][0]):.6f}°): are the GPS angles in the unit [gps] units "
                                    "says (deg or rad)?"])
        kw["initial"] = {**{k: i[k] for k in ("lat_deg", "lon_deg", "height_m", "vel_ned")},
                         **{f"{a}_rad": math.radians(float(i[f"{a}_deg"])) for a in ("roll", "pitch", "yaw")},
                         **{k: i[k] for k in ("accel_bias", "gyro_bias") if k in i}}
    return from_geodetic(
        imu_t=imu["t"], imu_f=np.column_stack([imu["fx"], imu["fy"], imu["fz"]]),
        imu_w=np.column_stack([imu["wx"], imu["wy"], imu["wz"]]), imu_grade=spec.get("imu_grade", "navigation"),
        gps_t=gps["t"], lat_deg=np.degrees(gps["lat"]), lon_deg=np.degrees(gps["lon"]), height_m=gps["height"],
        roll_rad=gps["roll"], pitch_rad=gps["pitch"], yaw_rad=gps["yaw"], vel_ned=vel,
        init_sigma=spec.get("initial_sigma"), mount_quat=spec.get("mount_quat_bs", (1.0, 0, 0, 0)),
        mount_lever=spec.get("mount_lever_b", (0.0, 0, 0)), vertical_datum=str(spec.get("vertical_datum", "")),
        dem_reference=str(spec.get("dem", "")), name=str(spec.get("name", path.stem)), settings=settings, **kw)


def _number(value) -> bool:
    """A finite TOML number (not a boolean, a string or a list)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


MAX_GPS_SPEED_MPS = 1000.0
"""Horizontal speed between two GPS fixes above which (beyond 50 m of noise) a fix is a jump, not a flight."""
EDGE_S = 1.0
"""How far (s) scans and altimeter readings may lie outside the IMU's time span."""


def _distance_km(lat1: float, lon1: float, lat2: float, lon2: float) -> float:
    """Great-circle distance (km, a 6371 km sphere) between two points in degrees."""
    p1, p2 = math.radians(lat1), math.radians(lat2)
    h = math.sin((p2 - p1) / 2) ** 2 + math.cos(p1) * math.cos(p2) * math.sin(math.radians(lon2 - lon1) / 2) ** 2
    return 2.0 * 6371.0 * math.asin(min(1.0, math.sqrt(h)))


def _check_streams(spec: dict, data: dict) -> list[str]:
    """What the tables' values say against each other (the stated IMU rate against its samples' times is the log's
    own check, :meth:`~warptan.io.flightlog.FlightLog.validate`): a stated rate that is not a number, readings
    outside the IMU's time span, GPS jumps (a 1.1 km and a 111 km jump had been taken as the filter's error)."""
    problems = []
    imu_t, gps = data["imu"]["t"], data["gps"]
    if len(imu_t) < 2:
        return ["[imu] needs at least two samples"]
    rate = spec.get("imu_rate_hz")
    if rate is not None and not (_number(rate) and rate > 0):
        problems.append(f"imu_rate_hz = {rate!r} must be a positive number of Hz")
    lo, hi = float(imu_t[0]) - EDGE_S, float(imu_t[-1]) + EDGE_S
    for table in ("scans", "altimeter", "gps"):
        t = data.get(table, {}).get("t")
        if t is not None and len(t):
            out = int(np.count_nonzero((t < lo) | (t > hi)))
            if out:
                problems.append(f"[{table}] {out} of its {len(t)} rows lie outside the IMU's time span (t = "
                                f"{imu_t[0]:.3f} … {imu_t[-1]:.3f} s; they run {t[0]:.3f} … {t[-1]:.3f} s): "
                                "cut them, or give the IMU samples of that time")
    lat, lon, t = gps["lat"], gps["lon"], gps["t"]
    if len(t) > 1 and np.all(np.abs(lat) <= math.pi / 2):  # (latitudes out of range: from_geodetic says so)
        north = np.diff(lat) * 6371000.0
        east = np.diff(lon) * 6371000.0 * np.cos(lat[:-1])
        jump = np.hypot(north, east) > 50.0 + MAX_GPS_SPEED_MPS * np.diff(t)
        if jump.any():
            k = int(np.argmax(jump))
            problems.append(f"[gps] a jump of {np.hypot(north[k], east[k]) / 1000.0:.3g} km in {t[k + 1] - t[k]:.3g} s "
                            f"at t = {t[k + 1]:.3f} s ({int(jump.sum())} jump(s) faster than "
                            f"{MAX_GPS_SPEED_MPS:g} m/s): cut or repair the fixes")
    return problems


def write_tables(log: FlightLog, folder: str | os.PathLike) -> Path:
    """Write ``log`` (with truth and a geodetic frame) as CSV tables and ``layout.toml`` in ``folder``: the GPS
    columns are latitude/longitude/height and true-north roll/pitch/yaw and velocity, as a vehicle records them
    (full float precision). Returns the layout's path."""
    if log.frame is None or not log.has_truth:
        raise LogError(f"flight log {log.name}", ["tables need a log with truth and a geodetic frame (version 2)"])
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fmt = "%.17g"
    frame = log.frame
    lat, lon = frame.ne_to_latlon(log.truth_pos[:, 0], log.truth_pos[:, 1])
    turn = _north_turn(frame, lat, lon)
    euler = quat_to_euler(log.truth_quat)
    vel = turn_vectors(-turn, log.truth_vel)
    gps = np.column_stack([log.truth_t, lat, lon, frame.origin_height_m - log.truth_pos[:, 2],
                           np.degrees(euler[:, 0]), np.degrees(euler[:, 1]), np.degrees(euler[:, 2] - turn), vel])
    np.savetxt(folder / "gps.csv", gps, delimiter=",", fmt=fmt, comments="",
               header="t,lat,lon,height,roll,pitch,yaw,vn,ve,vd")
    np.savetxt(folder / "imu.csv", np.column_stack([log.imu_t, log.imu_f, log.imu_w]), delimiter=",", fmt=fmt,
               comments="", header="t,fx,fy,fz,wx,wy,wz")
    la0, lo0 = frame.ne_to_latlon(log.init_pos[:1], log.init_pos[1:2])
    t0 = float(_north_turn(frame, la0, lo0)[0])
    e0 = quat_to_euler(log.init_quat[None])[0]
    lines = [f"name = {_q(log.name)}", f"dem = {_q(log.dem_reference)}",
             f"vertical_datum = {_q(frame.vertical_datum)}", f"imu_grade = {_q(log.imu_grade)}",
             f"imu_rate_hz = {log.imu_rate_hz!r}", f"initial_sigma = {_a(log.init_sigma)}",
             f"range_sigma_m = {log.range_sigma_m!r}", f"altimeter_sigma_m = {log.altimeter_sigma_m!r}",
             f"baro_sigma_m = {log.baro_sigma_m!r}", f"mount_quat_bs = {_a(log.mount_quat)}",
             f"mount_lever_b = {_a(log.mount_lever)}",
             f"settings_json = {_q(json.dumps(log.settings, sort_keys=True)) if log.settings else _q('')}",
             "", "[initial]  # the INS's initial state (the simulated vehicle's own navigation solution)",
             f"lat_deg = {float(la0[0])!r}", f"lon_deg = {float(lo0[0])!r}",
             f"height_m = {frame.origin_height_m - float(log.init_pos[2])!r}",
             f"roll_deg = {math.degrees(e0[0])!r}", f"pitch_deg = {math.degrees(e0[1])!r}",
             f"yaw_deg = {math.degrees(e0[2] - t0)!r}",
             f"vel_ned = {_a(turn_vectors(-t0, log.init_vel))}",
             f"accel_bias = {_a(log.init_accel_bias)}", f"gyro_bias = {_a(log.init_gyro_bias)}",
             "", "[imu]", 'file = "imu.csv"', 'units = {t = "s", fx = "m/s^2", wx = "rad/s"}',
             "", "[gps]", 'file = "gps.csv"',
             'units = {lat = "deg", lon = "deg", roll = "deg", pitch = "deg", yaw = "deg"}']
    if log.has_scans:
        pts = log.scan_ranges[..., None] * log.scan_dirs
        rows = np.column_stack([np.repeat(log.scan_t, pts.shape[1]), pts.reshape(-1, 3)])
        np.savetxt(folder / "scans.csv", rows, delimiter=",", fmt=fmt, comments="", header="t,x,y,z")
        lines += ["", "[scans]", 'file = "scans.csv"']
    if log.has_altimeter:
        np.savetxt(folder / "altimeter.csv", np.column_stack([log.alt_t, log.alt_range]), delimiter=",", fmt=fmt,
                   comments="", header="t,range")
        lines += ["", "[altimeter]", 'file = "altimeter.csv"']
    if log.baro_t is not None:
        np.savetxt(folder / "baro.csv", np.column_stack([log.baro_t, log.baro_alt]), delimiter=",", fmt=fmt,
                   comments="", header="t,alt")
        lines += ["", "[baro]", 'file = "baro.csv"']
    text = "\n".join(lines) + "\n"
    (folder / "layout.toml").write_text(text)
    return folder / "layout.toml"


def _a(values) -> str:
    return "[" + ", ".join(repr(float(x)) for x in values) + "]"


def _q(text: str) -> str:
    return '"' + str(text).replace("\\", "\\\\").replace('"', '\\"') + '"'
