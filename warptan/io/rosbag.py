"""ROS 2 bags in and out (``rosbags``, pure Python, no ROS install): a bag becomes a
:class:`~warptan.io.flightlog.FlightLog`, and a flight log can be written as a bag (``warptan run --export-bag``).

Topics (names in :class:`BagConfig`, a small TOML or the command line):

* ``sensor_msgs/Imu``: ``linear_acceleration`` (specific force) and ``angular_velocity`` in the body frame, FLU;
* ``sensor_msgs/PointCloud2``: points ``x, y, z`` (FLOAT32 or FLOAT64) in the sensor frame, FLU; a point with a
  NaN coordinate is no return;
* ``sensor_msgs/Range``: the radar altimeter (``range`` outside ``[min_range, max_range]`` or NaN: no return);
* ``sensor_msgs/FluidPressure``: the barometer, Pa, turned into altitude by the ICAO standard atmosphere
  (``h = 44330.77 (1 - (p / 101325)^0.190263)`` m);
* ``nav_msgs/Odometry`` (optional truth): pose of the body (``child_frame_id``, FLU) in an ENU map frame whose
  east/north axes are the log's map frame (the geodetic frame of the TOML's ``frame_*`` keys, else the
  DEM's grid); twist in the body frame (REP 103/105).

Frames: ROS uses FLU bodies and ENU worlds, warptan FRD and NED. Vectors in a body or sensor frame change by
``C = diag(1, -1, -1)`` (FLU ↔ FRD); map positions by ``(x, y, z)_ENU → (y, x, -z)_NED``; attitudes by
``R_nb = M R_enu_flu C`` with ``M`` the ENU → NED axis swap. The mounting in the TOML is ROS's: the sensor frame's
rotation in the body frame (``mount_quat_xyzw``, FLU) and its origin (``mount_lever_m``, FLU), as ``tf2`` reports
them. Header stamps are the sample times. Message fields ROS defines as float32 (``Range.range``) carry float32
precision (0.06 mm at 1 km).

The bag does not carry what a filter needs besides the sensors — the initial nominal state and its σ, the IMU grade,
the DEM — so these come from the TOML; ``warptan run --export-bag`` writes one (``warptan.toml`` in the bag folder,
read by default) with the exported flight's values and filter settings.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

from warptan.io.flightlog import FlightLog, LogError
from warptan.nav.frames import mat_to_quat, quat_to_mat
from warptan.nav.geoframe import GeoFrame

FLU_FRD = np.diag([1.0, -1.0, -1.0])
"""Vectors in a FLU frame to the same body's FRD frame (and back: it is its own inverse)."""
ENU_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""ENU map vectors to NED (its own inverse)."""
SIDECAR = "warptan.toml"
P0_PA = 101325.0


def pressure_to_altitude(p_pa):
    """ICAO standard atmosphere (troposphere): altitude in m from static pressure in Pa."""
    return 44330.77 * (1.0 - (np.asarray(p_pa, dtype=np.float64) / P0_PA) ** 0.190263)


def altitude_to_pressure(h_m):
    """Inverse of :func:`pressure_to_altitude`."""
    return P0_PA * (1.0 - np.asarray(h_m, dtype=np.float64) / 44330.77) ** (1.0 / 0.190263)


def quat_ros_to_ned(q_xyzw) -> np.ndarray:
    """(T, 4) ROS orientations [x, y, z, w] of FLU bodies in ENU → warptan [w, x, y, z] of FRD bodies in NED."""
    q = np.atleast_2d(np.asarray(q_xyzw, dtype=np.float64))
    r = quat_to_mat(q[:, [3, 0, 1, 2]])
    out = mat_to_quat(ENU_NED @ r @ FLU_FRD)
    return np.atleast_2d(out)


def quat_ned_to_ros(q_wxyz) -> np.ndarray:
    """Inverse of :func:`quat_ros_to_ned`: (T, 4) [x, y, z, w]."""
    q = np.atleast_2d(np.asarray(q_wxyz, dtype=np.float64))
    out = np.atleast_2d(mat_to_quat(ENU_NED @ quat_to_mat(q) @ FLU_FRD))
    return out[:, [1, 2, 3, 0]]


@dataclass(frozen=True)
class BagConfig:
    """What a bag needs beside its messages. Attributes: topic names, the IMU grade and nominal rate (0: the median
    sample rate), the mounting (ROS convention), the initial state (NED, warptan convention; None: the first
    odometry message) and its σ (15: pos m, vel m/s, attitude rad, accel bias m/s², gyro bias rad/s), sensor σ,
    the DEM (and its posts, ``dem_posts``), the map frame on the Earth (``frame_origin_lat_deg``,
    ``frame_origin_lon_deg``, ``frame_origin_height_m``, ``frame_vertical_datum``:
    :class:`~warptan.nav.geoframe.GeoFrame`; without a latitude the ENU frame is the DEM's grid) and optional filter
    settings (JSON)."""

    imu: str = "/imu"
    cloud: str = "/points"
    range: str = "/altimeter"
    baro: str = "/baro"
    odom: str = "/truth"
    grade: str = "navigation"
    imu_rate_hz: float = 0.0
    mount_quat_xyzw: tuple = (0.0, 0.0, 0.0, 1.0)
    mount_lever_m: tuple = (0.0, 0.0, 0.0)
    initial_pos_n: tuple | None = None
    initial_vel_n: tuple | None = None
    initial_quat_nb: tuple | None = None
    initial_sigma: tuple = (100.0, 100.0, 20.0, 0.5, 0.5, 0.5, 0.0017453292519943296, 0.0017453292519943296,
                            0.008726646259971648, 0.000980665, 0.000980665, 0.000980665, 4.84813681109536e-08,
                            4.84813681109536e-08, 4.84813681109536e-08)
    range_sigma_m: float = 0.5
    altimeter_sigma_m: float = 1.0
    baro_sigma_m: float = 1.0
    dem: str = ""
    frame_origin_lat_deg: float | None = None
    frame_origin_lon_deg: float | None = None
    frame_origin_height_m: float = 0.0
    frame_vertical_datum: str = ""
    dem_posts: tuple | None = None
    """The DEM's posts in the map frame (:attr:`warptan.io.flightlog.FlightLog.dem_posts`; None: not recorded)."""
    settings_json: str = ""

    @property
    def frame(self) -> GeoFrame | None:
        if self.frame_origin_lat_deg is None and self.frame_origin_lon_deg is None:
            return None
        return GeoFrame(self.frame_origin_lat_deg, self.frame_origin_lon_deg, self.frame_origin_height_m,
                        self.frame_vertical_datum)

    @classmethod
    def load(cls, path) -> BagConfig:
        """From a TOML file (keys as the attributes); an unknown key is an error naming it."""
        path = Path(path)
        try:
            data = tomllib.loads(path.read_text())
        except (OSError, tomllib.TOMLDecodeError) as err:
            raise LogError(f"bag config {path}", [f"does not load: {err}"]) from None
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(data) - known)
        if unknown:
            raise LogError(f"bag config {path}", [f"unknown key(s) {', '.join(unknown)} (known: "
                                                  f"{', '.join(sorted(known))})"])
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})

    @classmethod
    def for_bag(cls, path) -> BagConfig:
        """The bag's own ``warptan.toml`` (beside its metadata) when it has one, else the defaults."""
        path = Path(path)
        sidecar = (path if path.is_dir() else path.parent) / SIDECAR
        return cls.load(sidecar) if sidecar.is_file() else cls()

    def with_overrides(self, **values) -> BagConfig:
        return replace(self, **{k: v for k, v in values.items() if v is not None})

    def to_toml(self) -> str:
        lines = []
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if value is None:
                continue
            if isinstance(value, str):
                lines.append(f"{name} = {json.dumps(value)}")
            elif isinstance(value, (tuple, list)):
                lines.append(f"{name} = [{', '.join(repr(float(v)) for v in value)}]")
            else:
                lines.append(f"{name} = {float(value)!r}")
        return "\n".join(lines) + "\n"


def _stamp(t: float):
    sec = math.floor(t)
    nsec = round((t - sec) * 1e9)
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return int(sec), nsec


def _time(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def write_bag(log: FlightLog, path) -> Path:
    """Write ``log`` as a ROS 2 bag folder ``path`` (SQLite3) with FLU/ENU topics, and ``path/warptan.toml`` with
    the rest (initial state and σ, grade, DEM, filter settings)."""
    from rosbags.rosbag2 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    T = ts.types
    path = Path(path)
    cfg = BagConfig(imu_rate_hz=log.imu_rate_hz, grade=log.imu_grade,
                    mount_quat_xyzw=tuple(quat_ned_to_ros_mount(log.mount_quat)),
                    mount_lever_m=tuple(FLU_FRD @ log.mount_lever), initial_pos_n=tuple(log.init_pos),
                    initial_vel_n=tuple(log.init_vel), initial_quat_nb=tuple(log.init_quat),
                    initial_sigma=tuple(log.init_sigma), range_sigma_m=log.range_sigma_m,
                    altimeter_sigma_m=log.altimeter_sigma_m, baro_sigma_m=log.baro_sigma_m, dem=log.dem_reference,
                    **({} if log.frame is None else {f"frame_{k}": v for k, v in asdict(log.frame).items()}),
                    dem_posts=None if log.dem_posts is None else tuple(float(v) for v in log.dem_posts),
                    settings_json=json.dumps(log.settings, sort_keys=True) if log.settings else "")

    def header(t, frame):
        sec, nsec = _stamp(t)
        return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id=frame)

    def vec(v):
        return T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def quat(q):
        return T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))

    zeros9 = np.zeros(9)
    messages = []  # (t, topic, msgtype, message)
    f_flu, w_flu = log.imu_f @ FLU_FRD, log.imu_w @ FLU_FRD
    for k, t in enumerate(log.imu_t):
        messages.append((t, cfg.imu, "sensor_msgs/msg/Imu", T["sensor_msgs/msg/Imu"](
            header=header(t, "base_link"), orientation=quat([0.0, 0.0, 0.0, 1.0]),
            orientation_covariance=np.r_[-1.0, np.zeros(8)], angular_velocity=vec(w_flu[k]),
            angular_velocity_covariance=zeros9, linear_acceleration=vec(f_flu[k]),
            linear_acceleration_covariance=zeros9)))
    if log.has_scans:
        PF = T["sensor_msgs/msg/PointField"]
        fields = [PF(name=n, offset=8 * i, datatype=8, count=1) for i, n in enumerate("xyz")]
        for j, t in enumerate(log.scan_t):
            pts = np.where(log.scan_valid[j][:, None], log.scan_ranges[j][:, None] * log.scan_dirs[j], np.nan)
            data = np.ascontiguousarray(pts @ FLU_FRD, dtype="<f8").view(np.uint8).ravel()
            messages.append((t, cfg.cloud, "sensor_msgs/msg/PointCloud2", T["sensor_msgs/msg/PointCloud2"](
                header=header(t, "sensor"), height=1, width=len(pts), fields=fields, is_bigendian=False,
                point_step=24, row_step=24 * len(pts), data=data, is_dense=False)))
    if log.has_altimeter:
        for j, t in enumerate(log.alt_t):
            r = float(log.alt_range[j])
            messages.append((t, cfg.range, "sensor_msgs/msg/Range", T["sensor_msgs/msg/Range"](
                header=header(t, "altimeter"), radiation_type=2, field_of_view=0.1, min_range=0.0,
                max_range=1.0e5, range=r if np.isfinite(r) else float("nan"))))
    if log.baro_t is not None:
        press = altitude_to_pressure(log.baro_alt)
        for j, t in enumerate(log.baro_t):
            messages.append((t, cfg.baro, "sensor_msgs/msg/FluidPressure", T["sensor_msgs/msg/FluidPressure"](
                header=header(t, "baro"), fluid_pressure=float(press[j]), variance=0.0)))
    if log.has_truth:
        q_ros = quat_ned_to_ros(log.truth_quat)
        rot = quat_to_mat(log.truth_quat)
        v_body = np.einsum("tji,tj->ti", rot, log.truth_vel) @ FLU_FRD
        pos_enu = log.truth_pos @ ENU_NED
        P = T["geometry_msgs/msg/Point"]
        for j, t in enumerate(log.truth_t):
            pose = T["geometry_msgs/msg/Pose"](position=P(x=float(pos_enu[j, 0]), y=float(pos_enu[j, 1]),
                                                          z=float(pos_enu[j, 2])), orientation=quat(q_ros[j]))
            twist = T["geometry_msgs/msg/Twist"](linear=vec(v_body[j]), angular=vec([0.0, 0.0, 0.0]))
            messages.append((t, cfg.odom, "nav_msgs/msg/Odometry", T["nav_msgs/msg/Odometry"](
                header=header(t, "map"), child_frame_id="base_link",
                pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
                twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))))
    messages.sort(key=lambda m: m[0])
    with Writer(path, version=8) as writer:
        conns = {}
        for _, topic, msgtype, _ in messages:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=ts)
        for t, topic, msgtype, msg in messages:
            sec, nsec = _stamp(t)
            writer.write(conns[topic], sec * 1_000_000_000 + nsec, ts.serialize_cdr(msg, msgtype))
    (path / SIDECAR).write_text(cfg.to_toml())
    return path


def quat_ned_to_ros_mount(q_bs) -> np.ndarray:
    """warptan's mounting (sensor FRD → body FRD, [w, x, y, z]) as ROS's (sensor FLU in body FLU, [x, y, z, w])."""
    q = mat_to_quat(FLU_FRD @ quat_to_mat(np.asarray(q_bs, dtype=np.float64)) @ FLU_FRD)
    return np.asarray(q)[[1, 2, 3, 0]]


def _mount_from_ros(q_xyzw) -> np.ndarray:
    q = np.asarray(q_xyzw, dtype=np.float64)[[3, 0, 1, 2]]
    if np.allclose(q, [1.0, 0.0, 0.0, 0.0], rtol=0, atol=0):
        return q
    return np.asarray(mat_to_quat(FLU_FRD @ quat_to_mat(q / np.linalg.norm(q)) @ FLU_FRD))


def _cloud_points(msg) -> np.ndarray:
    """(M, 3) float64 x, y, z of a PointCloud2 (FLOAT32 or FLOAT64 fields, any point layout)."""
    fields = {f.name: f for f in msg.fields}
    if not {"x", "y", "z"} <= set(fields):
        raise ValueError(f"PointCloud2 without x, y, z fields (has {', '.join(fields) or 'none'})")
    kinds = {7: "f4", 8: "f8"}
    n = msg.width * msg.height
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    out = np.empty((n, 3))
    for i, name in enumerate("xyz"):
        f = fields[name]
        if f.datatype not in kinds:
            raise ValueError(f"PointCloud2 field {name} has datatype {f.datatype} (FLOAT32 = 7 or FLOAT64 = 8 only)")
        dt = np.dtype(kinds[f.datatype]).newbyteorder(">" if msg.is_bigendian else "<")
        out[:, i] = np.ndarray((n,), dtype=dt, buffer=raw, offset=f.offset, strides=(msg.point_step,))
    return out


def read_bag(path, config: BagConfig | None = None) -> FlightLog:
    """A ROS 2 bag (folder, or its .db3/.mcap file) as a validated :class:`FlightLog`. ``config`` default: the bag's
    ``warptan.toml`` when it has one, else :class:`BagConfig` defaults. Missing topics and bad messages are listed
    together in one :class:`LogError`."""
    from rosbags.rosbag2 import Reader
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    folder = path if path.is_dir() else path.parent
    source = f"ROS 2 bag {path}"
    if config is None:
        config = BagConfig.for_bag(path)
    ts = get_typestore(Stores.ROS2_HUMBLE)
    streams: dict[str, list] = {k: [] for k in ("imu", "cloud", "range", "baro", "odom")}
    want = {config.imu: "imu", config.cloud: "cloud", config.range: "range", config.baro: "baro",
            config.odom: "odom"}
    problems = []
    try:
        reader = Reader(folder)
        reader.open()
    except Exception as err:  # rosbags raises its own error types for every unreadable bag
        raise LogError(source, [f"not a readable ROS 2 bag ({err})"]) from None
    try:
        topics = {c.topic: c.msgtype for c in reader.connections}
        if config.imu not in topics:
            problems.append(f"IMU topic {config.imu!r} is not in the bag (topics: {', '.join(sorted(topics))})")
        if config.cloud not in topics and config.range not in topics:
            problems.append(f"neither the point-cloud topic {config.cloud!r} nor the altimeter topic {config.range!r} "
                            f"is in the bag (topics: {', '.join(sorted(topics))})")
        if problems:
            raise LogError(source, problems)
        conns = [c for c in reader.connections if c.topic in want]
        for conn, _, raw in reader.messages(connections=conns):
            msg = ts.deserialize_cdr(raw, conn.msgtype)
            streams[want[conn.topic]].append(msg)
    finally:
        reader.close()
    kw: dict = {}
    imu = streams["imu"]
    kw["imu_t"] = np.array([_time(m.header) for m in imu])
    kw["imu_f"] = np.array([[m.linear_acceleration.x, m.linear_acceleration.y, m.linear_acceleration.z]
                            for m in imu]).reshape(-1, 3) @ FLU_FRD
    kw["imu_w"] = np.array([[m.angular_velocity.x, m.angular_velocity.y, m.angular_velocity.z]
                            for m in imu]).reshape(-1, 3) @ FLU_FRD
    steps = np.diff(kw["imu_t"])
    rate = config.imu_rate_hz or (1.0 / float(np.median(steps)) if len(steps) else 0.0)
    kw["imu_rate_hz"] = float(rate)
    kw["t_end"] = float(kw["imu_t"][-1] + 1.0 / rate) if len(kw["imu_t"]) and rate > 0 else math.nan
    if streams["cloud"]:
        clouds = []
        for j, m in enumerate(streams["cloud"]):
            try:
                clouds.append(_cloud_points(m) @ FLU_FRD)
            except ValueError as err:
                problems.append(f"{config.cloud} message {j}: {err}")
        if clouds and len({len(c) for c in clouds}) > 1:
            m_max = max(len(c) for c in clouds)
            clouds = [np.vstack([c, np.full((m_max - len(c), 3), np.nan)]) for c in clouds]
        if clouds:
            pts = np.array(clouds)
            r = np.linalg.norm(pts, axis=2)
            valid = np.isfinite(r) & (r > 0)
            kw.update(scan_t=np.array([_time(m.header) for m in streams["cloud"]]),
                      scan_ranges=np.where(valid, r, np.nan),
                      scan_dirs=np.where(valid[..., None], pts / np.where(valid, r, 1.0)[..., None], np.nan),
                      scan_valid=valid)
    if streams["range"]:
        rng = np.array([m.range if m.min_range <= m.range <= m.max_range else np.nan for m in streams["range"]],
                       dtype=np.float64)
        kw.update(alt_t=np.array([_time(m.header) for m in streams["range"]]), alt_range=rng)
    if streams["baro"]:
        kw.update(baro_t=np.array([_time(m.header) for m in streams["baro"]]),
                  baro_alt=pressure_to_altitude([m.fluid_pressure for m in streams["baro"]]))
    odom = streams["odom"]
    if odom:
        pos_enu = np.array([[m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z] for m in odom])
        q_ros = np.array([[m.pose.pose.orientation.x, m.pose.pose.orientation.y, m.pose.pose.orientation.z,
                           m.pose.pose.orientation.w] for m in odom])
        quat = quat_ros_to_ned(q_ros)
        v_body = np.array([[m.twist.twist.linear.x, m.twist.twist.linear.y, m.twist.twist.linear.z]
                           for m in odom]) @ FLU_FRD
        kw.update(truth_t=np.array([_time(m.header) for m in odom]), truth_pos=pos_enu @ ENU_NED,
                  truth_quat=quat, truth_vel=np.einsum("tij,tj->ti", quat_to_mat(quat), v_body))
    initial = [config.initial_pos_n, config.initial_vel_n, config.initial_quat_nb]
    if all(v is not None for v in initial):
        kw.update(init_pos=np.array(initial[0], dtype=np.float64), init_vel=np.array(initial[1], dtype=np.float64),
                  init_quat=np.array(initial[2], dtype=np.float64))
    elif odom:  # the truth at the first IMU sample
        t0 = kw["imu_t"][:1]
        from warptan.io.flightlog import sample_at

        kw.update(init_pos=sample_at(kw["truth_t"], kw["truth_pos"], t0)[0],
                  init_vel=sample_at(kw["truth_t"], kw["truth_vel"], t0)[0],
                  init_quat=sample_at(kw["truth_t"], kw["truth_quat"], t0, unit=True)[0])
    else:
        problems.append("no initial state: give initial_pos_n, initial_vel_n, initial_quat_nb in the bag config, or "
                        f"an odometry topic ({config.odom!r})")
    if problems:
        raise LogError(source, problems)
    kw["init_t"] = float(kw["imu_t"][0]) if len(kw["imu_t"]) else math.nan
    settings = json.loads(config.settings_json) if config.settings_json else {}
    log = FlightLog(imu_grade=config.grade, init_sigma=np.array(config.initial_sigma, dtype=np.float64),
                    range_sigma_m=config.range_sigma_m, altimeter_sigma_m=config.altimeter_sigma_m,
                    baro_sigma_m=config.baro_sigma_m, mount_quat=_mount_from_ros(config.mount_quat_xyzw),
                    mount_lever=FLU_FRD @ np.array(config.mount_lever_m, dtype=np.float64), dem_reference=config.dem,
                    dem_posts=None if config.dem_posts is None else np.array(config.dem_posts, dtype=np.float64),
                    frame=config.frame, settings=settings, name=folder.name, **kw)
    return log.validate(source)
