"""Strapdown INS: the nominal mechanization and its error-state model (design notes §3; Solà 2017 §5.4; paper §II).

Mechanization per IMU sample ``(f~, w~)`` with period ``dt`` and constant nominal biases ``ba, bg``::

    a_n = R(q) (f~ - ba) + g_n
    p  <- p + v dt + 0.5 a_n dt^2
    v  <- v + a_n dt
    q  <- q ⊗ Exp((w~ - bg) dt)

The INS runs open loop. Error state ``dx = [dp, dv, dth, dba, dbg]`` (15) with true = nominal ⊕ error:
``p = p_nom + dp``, ``v = v_nom + dv``, ``q = q_nom ⊗ Exp(dth)``, ``ba = ba_nom + dba``, ``bg = bg_nom + dbg``.

:func:`error_transition` returns the discrete transition ``F`` (15×15). With ``exact=False`` it is design notes §3
(Solà's first-order form); with ``exact=True`` (default) it is the exact Jacobian of the discrete
mechanization above: the position row also gets ``0.5 dt² (-R [a]x dth - R dba)`` and the gyro-bias
column of the attitude row uses the right Jacobian ``-J_r(w dt) dt``; both differ from the design notes' (§3) by O(dt²).
:func:`process_noise` returns ``Q`` (15×15) from the noise densities.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from warptan.checks import LOCAL_FRAME_M, FilterError
from warptan.nav.frames import check_unit_quat, quat_conj, quat_exp, quat_log, quat_mul
from warptan.nav.imu import ImuGrade, check_rate

GRAVITY_N = np.array([0.0, 0.0, 9.80665])
"""Gravity in NED, m/s² (flat earth, design notes §1)."""


@dataclass
class NavState:
    """A navigation state, float64 on the host.

    Attributes:
        pos_n: (3,) NED position, m.
        vel_n: (3,) NED velocity, m/s.
        quat_nb: (4,) attitude [w, x, y, z], body to navigation.
        accel_bias: (3,) accelerometer bias, m/s².
        gyro_bias: (3,) gyro bias, rad/s.
    """

    pos_n: np.ndarray
    vel_n: np.ndarray
    quat_nb: np.ndarray
    accel_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gyro_bias: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self):
        for name in ("pos_n", "vel_n", "accel_bias", "gyro_bias"):
            value = np.array(getattr(self, name), dtype=np.float64).reshape(-1)
            if value.shape != (3,) or not np.isfinite(value).all():
                raise FilterError(f"NavState.{name} must be 3 finite numbers, got {getattr(self, name)!r}")
            if name == "pos_n" and np.abs(value).max() > LOCAL_FRAME_M:
                raise FilterError(f"NavState.pos_n = {value.tolist()} is more than {LOCAL_FRAME_M:g} m from the NED "
                                 "origin: not a position in a local frame (the particles' float32 poses lose it)")
            setattr(self, name, value)
        self.quat_nb = check_unit_quat(np.array(self.quat_nb, dtype=np.float64).reshape(-1), "NavState.quat_nb")

    def copy(self) -> NavState:
        """A deep copy."""
        return NavState(self.pos_n.copy(), self.vel_n.copy(), self.quat_nb.copy(), self.accel_bias.copy(),
                        self.gyro_bias.copy())


def _check_sample(f, w) -> tuple[np.ndarray, np.ndarray]:
    f = np.asarray(f, dtype=np.float64).reshape(3)
    w = np.asarray(w, dtype=np.float64).reshape(3)
    if not (np.isfinite(f).all() and np.isfinite(w).all()):
        raise FilterError(f"non-finite IMU sample: specific force {f}, body rate {w}")
    return f, w


def mechanize(state: NavState, f_b, w_b, dt: float) -> NavState:
    """One step of the nominal mechanization; returns a new state.

    Args:
        state: Current state.
        f_b: (3,) measured specific force, body frame, m/s².
        w_b: (3,) measured body rate, rad/s.
        dt: Sample period, s.

    Raises:
        ValueError: a NaN or inf sample (the state is never propagated with it).
    """
    f, w = _check_sample(f_b, w_b)
    out = state.copy()
    _step_inplace(out.pos_n, out.vel_n, out.quat_nb, out.accel_bias, out.gyro_bias, f, w, dt)
    return out


def _step_inplace(p, v, q, ba, bg, f, w, dt) -> None:
    """The mechanization on plain arrays, in place (no validation: callers check their inputs once)."""
    qw, qx, qy, qz = q
    fx, fy, fz = f[0] - ba[0], f[1] - ba[1], f[2] - ba[2]
    # a_n = R(q) (f - ba) + g
    ax = (1 - 2 * (qy * qy + qz * qz)) * fx + 2 * (qx * qy - qw * qz) * fy + 2 * (qx * qz + qw * qy) * fz
    ay = 2 * (qx * qy + qw * qz) * fx + (1 - 2 * (qx * qx + qz * qz)) * fy + 2 * (qy * qz - qw * qx) * fz
    az = 2 * (qx * qz - qw * qy) * fx + 2 * (qy * qz + qw * qx) * fy + (1 - 2 * (qx * qx + qy * qy)) * fz
    az += GRAVITY_N[2]
    half = 0.5 * dt * dt
    p[0] += v[0] * dt + half * ax
    p[1] += v[1] * dt + half * ay
    p[2] += v[2] * dt + half * az
    v[0] += ax * dt
    v[1] += ay * dt
    v[2] += az * dt
    # q <- q ⊗ Exp((w - bg) dt)
    rx, ry, rz = (w[0] - bg[0]) * dt, (w[1] - bg[1]) * dt, (w[2] - bg[2]) * dt
    angle = math.sqrt(rx * rx + ry * ry + rz * rz)
    if angle < 1e-8:
        ew, sc = 1.0 - angle * angle / 8.0, 0.5 - angle * angle / 48.0
    else:
        ew, sc = math.cos(0.5 * angle), math.sin(0.5 * angle) / angle
    ex, ey, ez = sc * rx, sc * ry, sc * rz
    nw = qw * ew - qx * ex - qy * ey - qz * ez
    nx = qw * ex + qx * ew + qy * ez - qz * ey
    ny = qw * ey - qx * ez + qy * ew + qz * ex
    nz = qw * ez + qx * ey - qy * ex + qz * ew
    norm = math.sqrt(nw * nw + nx * nx + ny * ny + nz * nz)
    q[0], q[1], q[2], q[3] = nw / norm, nx / norm, ny / norm, nz / norm


class Ins:
    """The open-loop nominal INS.

    Args:
        initial: The initial nominal state.
        rate_hz: IMU rate, Hz.
    """

    def __init__(self, initial: NavState, rate_hz: float):
        self.state = initial.copy()
        self.rate_hz = check_rate(rate_hz)
        self.dt = 1.0 / self.rate_hz

    def step(self, f_b, w_b) -> NavState:
        """Advance by one IMU sample (in place); returns the state."""
        f, w = _check_sample(f_b, w_b)
        s = self.state
        _step_inplace(s.pos_n, s.vel_n, s.quat_nb, s.accel_bias, s.gyro_bias, f, w, self.dt)
        return s

    def run(self, f_b, w_b, dt=None) -> dict[str, np.ndarray]:
        """Propagate through (K, 3) samples (``dt``: each sample's step, (K,) s; default the nominal step);
        returns the K+1 states as arrays ``pos_n, vel_n, quat_nb``."""
        f_b = np.asarray(f_b, dtype=np.float64)
        w_b = np.asarray(w_b, dtype=np.float64)
        if f_b.shape != w_b.shape or f_b.ndim != 2 or f_b.shape[1] != 3:
            raise FilterError(f"IMU samples must be two (K, 3) arrays, got {f_b.shape} and {w_b.shape}")
        bad = ~(np.isfinite(f_b).all(axis=1) & np.isfinite(w_b).all(axis=1))
        if bad.any():
            raise FilterError(f"{bad.sum()} IMU samples are not finite (first at index {int(np.argmax(bad))})")
        k = len(f_b)
        pos, vel, quat = np.empty((k + 1, 3)), np.empty((k + 1, 3)), np.empty((k + 1, 4))
        s = self.state.copy()
        p, v, q = list(s.pos_n), list(s.vel_n), list(s.quat_nb)
        ba, bg = list(s.accel_bias), list(s.gyro_bias)
        pos[0], vel[0], quat[0] = p, v, q
        f_list, w_list = f_b.tolist(), w_b.tolist()
        steps = [self.dt] * k if dt is None else np.broadcast_to(np.asarray(dt, dtype=np.float64), (k,)).tolist()
        for i in range(k):
            _step_inplace(p, v, q, ba, bg, f_list[i], w_list[i], steps[i])
            pos[i + 1], vel[i + 1], quat[i + 1] = p, v, q
        self.state = NavState(p, v, q, ba, bg)
        return {"pos_n": pos, "vel_n": vel, "quat_nb": quat}


def _rot(q) -> np.ndarray:
    """``R(q)`` of one unit quaternion (fast scalar form of :func:`warptan.nav.frames.quat_to_mat`)."""
    w, x, y, z = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _skew3(v) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def error_transition(state: NavState, f_b, w_b, dt: float, exact: bool = True) -> np.ndarray:
    """Discrete error-state transition ``F`` (15×15) for one IMU step from ``state`` (see module doc)."""
    f, w = _check_sample(f_b, w_b)
    r = _rot(state.quat_nb)
    a = f - state.accel_bias
    wdt = (w - state.gyro_bias) * dt
    dv_dth = -(r @ _skew3(a)) * dt
    dv_dba = -r * dt
    # Exp(w dt) as a matrix (Rodrigues); its transpose maps the attitude error forward.
    angle = math.sqrt(float(wdt @ wdt))
    k = _skew3(wdt)
    if angle < 1e-8:
        c1, c2 = 1.0, 0.5
        j1, j2 = 0.5, 1.0 / 6.0
    else:
        c1, c2 = math.sin(angle) / angle, (1 - math.cos(angle)) / angle**2
        j1, j2 = c2, (angle - math.sin(angle)) / angle**3
    kk = k @ k
    exp_w = np.eye(3) + c1 * k + c2 * kk
    F = np.eye(15)
    F[0:3, 3:6] = np.eye(3) * dt
    F[3:6, 6:9] = dv_dth
    F[3:6, 9:12] = dv_dba
    F[6:9, 6:9] = exp_w.T
    if exact:
        F[0:3, 6:9] = 0.5 * dt * dv_dth
        F[0:3, 9:12] = 0.5 * dt * dv_dba
        F[6:9, 12:15] = -(np.eye(3) - j1 * k + j2 * kk) * dt  # -J_r(w dt) dt
    else:
        F[6:9, 12:15] = -np.eye(3) * dt
    return F


def process_noise(grade: ImuGrade, dt: float) -> np.ndarray:
    """``Q`` (15×15): ``Na² dt`` on dv, ``Ng² dt`` on dth, ``Ba² dt`` on dba, ``Bg² dt`` on dbg (design notes §3)."""
    q = np.zeros(15)
    q[3:6] = grade.accel_noise**2 * dt
    q[6:9] = grade.gyro_noise**2 * dt
    q[9:12] = grade.accel_bias_walk**2 * dt
    q[12:15] = grade.gyro_bias_walk**2 * dt
    return np.diag(q)


def state_difference(true: NavState, nominal: NavState) -> np.ndarray:
    """The error ``dx`` (15,) such that ``true = nominal ⊕ dx``."""
    return np.concatenate([
        true.pos_n - nominal.pos_n,
        true.vel_n - nominal.vel_n,
        quat_log(quat_mul(quat_conj(nominal.quat_nb), true.quat_nb)),
        true.accel_bias - nominal.accel_bias,
        true.gyro_bias - nominal.gyro_bias,
    ])


def state_plus(nominal: NavState, dx) -> NavState:
    """``nominal ⊕ dx``."""
    dx = np.asarray(dx, dtype=np.float64).reshape(15)
    q = quat_mul(nominal.quat_nb, quat_exp(dx[6:9]))
    return NavState(nominal.pos_n + dx[0:3], nominal.vel_n + dx[3:6], q / np.linalg.norm(q),
                    nominal.accel_bias + dx[9:12], nominal.gyro_bias + dx[12:15])
