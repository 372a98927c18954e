"""Truth trajectories: flights built from segments, with ideal IMU samples (design notes §4; paper §V).

The aircraft flies at constant airspeed ``V`` with its velocity along the body x axis (no angle of attack
or sideslip): pitch = flight-path angle γ, yaw = heading ψ, roll = bank φ, and coordinated turns have
``dψ/dt = g tan φ / V``. Bank and flight-path angle change smoothly (quintic "smootherstep", so body
rates and accelerations are continuous) over ``roll_time_s`` / ``transition_s``.

Consistency with the INS (design notes §4): the commanded attitude ``q_k`` and velocity ``v_k`` are sampled at
the IMU rate and the ideal samples are *derived* from them for the mechanization of :mod:`warptan.nav.ins`:
``w_k = Log(q_k^-1 ⊗ q_{k+1}) / dt`` and ``f_k = R(q_k)^T ((v_{k+1} - v_k) / dt - g_n)``, and the truth
position is ``p_{k+1} = p_k + v_k dt + 0.5 a_k dt²``. A perfect IMU therefore reproduces the truth to
floating-point error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from warptan.checks import FilterError, check_positive
from warptan.nav.frames import euler_to_quat, quat_conj, quat_log, quat_mul, quat_to_mat
from warptan.nav.imu import G0, check_rate
from warptan.nav.ins import GRAVITY_N, NavState


def smootherstep(x: np.ndarray) -> np.ndarray:
    """0 → 1 on [0, 1] with zero first and second derivatives at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


def _bank(value: float) -> float:
    b = float(value)
    if not (math.isfinite(b) and abs(b) < 90.0):
        raise FilterError(f"bank angle must be strictly between -90° and 90°, got {value!r}")
    return b


@dataclass(frozen=True)
class Straight:
    """Wings-level flight for ``duration_s`` at flight-path angle ``flight_path_deg`` (0 = level)."""

    duration_s: float
    flight_path_deg: float = 0.0


@dataclass(frozen=True)
class Climb:
    """Climb (or, negative, descent) at ``flight_path_deg`` for ``duration_s``, wings level."""

    duration_s: float
    flight_path_deg: float


@dataclass(frozen=True)
class Turn:
    """A coordinated turn through ``heading_change_deg`` (sign: + right, - left) at ``bank_deg`` (magnitude),
    rolling in and out over ``roll_time_s`` each; its duration follows from the heading change."""

    heading_change_deg: float
    bank_deg: float = 30.0
    roll_time_s: float = 3.0


@dataclass(frozen=True)
class Orbit:
    """Constant-bank circling for ``duration_s`` (roll-in and roll-out included) at ``bank_deg`` (+ right)."""

    duration_s: float
    bank_deg: float = 30.0
    roll_time_s: float = 3.0


Segment = Straight | Climb | Turn | Orbit


@dataclass
class Trajectory:
    """Truth at the IMU rate.

    Attributes:
        t_s: (K+1,) time, s.
        pos_n: (K+1, 3) NED position, m.
        vel_n: (K+1, 3) NED velocity, m/s.
        quat_nb: (K+1, 4) attitude [w, x, y, z].
        f_b: (K, 3) ideal specific force over each step, m/s².
        w_b: (K, 3) ideal body rate over each step, rad/s.
        rate_hz: IMU rate, Hz.
    """

    t_s: np.ndarray
    pos_n: np.ndarray
    vel_n: np.ndarray
    quat_nb: np.ndarray
    f_b: np.ndarray
    w_b: np.ndarray
    rate_hz: float

    @property
    def duration_s(self) -> float:
        """Length of the flight, s."""
        return float(self.t_s[-1])

    @property
    def euler_rad(self) -> np.ndarray:
        """(K+1, 3) roll, pitch, yaw in rad."""
        from warptan.nav.frames import quat_to_euler

        return quat_to_euler(self.quat_nb)

    def state(self, k: int = 0) -> NavState:
        """The true navigation state at sample ``k`` (zero biases: the truth has no IMU errors)."""
        return NavState(self.pos_n[k], self.vel_n[k], self.quat_nb[k])

    @classmethod
    def build(cls, segments: list[Segment], speed_mps: float, start_pos_n, heading_deg: float = 0.0,
              rate_hz: float = 100.0) -> Trajectory:
        """Fly ``segments`` in order from ``start_pos_n`` (NED, m; altitude = -z) at ``heading_deg``.

        Raises:
            ValueError: a non-positive speed, rate or duration, a bank of 90° or more, an empty segment
                list, a turn too short for its roll-in and roll-out, or an unknown segment.
        """
        speed = check_positive(speed_mps, "speed_mps")
        rate = check_rate(rate_hz)
        start = np.asarray(start_pos_n, dtype=np.float64).reshape(-1)
        if start.shape != (3,) or not np.isfinite(start).all():
            raise FilterError(f"start_pos_n must be 3 finite numbers, got {start_pos_n!r}")
        if not segments:
            raise FilterError("a trajectory needs at least one segment")
        plan = [_plan(seg, speed) for seg in segments]  # (duration, bank(τ) fn, flight path target)
        total = sum(p[0] for p in plan)
        n = round(total * rate)
        dt = 1.0 / rate
        t = np.arange(n + 1) * dt
        bank = np.zeros(n + 1)
        gamma = np.zeros(n + 1)
        t0, gamma_prev = 0.0, 0.0
        for duration, bank_fn, gamma_target, transition in plan:
            sel = (t >= t0 - 1e-9) & (t <= t0 + duration + 1e-9)
            tau = t[sel] - t0
            bank[sel] = bank_fn(tau)
            ramp = smootherstep(tau / transition) if transition > 0 else np.ones_like(tau)
            gamma[sel] = gamma_prev + (gamma_target - gamma_prev) * ramp
            t0 += duration
            gamma_prev = gamma_target
        rate_psi = G0 * np.tan(bank) / speed
        psi = math.radians(heading_deg) + np.concatenate([[0.0], np.cumsum(0.5 * (rate_psi[1:] + rate_psi[:-1]) * dt)])
        quat = euler_to_quat(bank, gamma, psi)
        vel = speed * np.stack([np.cos(gamma) * np.cos(psi), np.cos(gamma) * np.sin(psi), -np.sin(gamma)], axis=1)
        w_b = quat_log(quat_mul(quat_conj(quat[:-1]), quat[1:])) / dt
        acc = (vel[1:] - vel[:-1]) / dt
        f_b = np.einsum("kji,kj->ki", quat_to_mat(quat[:-1]), acc - GRAVITY_N)
        pos = np.empty((n + 1, 3))
        pos[0] = start
        pos[1:] = start + np.cumsum(0.5 * (vel[1:] + vel[:-1]) * dt, axis=0)
        return cls(t_s=t, pos_n=pos, vel_n=vel, quat_nb=quat, f_b=f_b, w_b=w_b, rate_hz=rate)


def _roll_profile(bank_rad: float, roll_time: float, duration: float):
    """Bank angle vs time in a segment: smooth roll-in over ``roll_time``, hold, smooth roll-out."""
    def fn(tau):
        rin = smootherstep(tau / roll_time) if roll_time > 0 else np.ones_like(tau)
        rout = smootherstep((duration - tau) / roll_time) if roll_time > 0 else np.ones_like(tau)
        return bank_rad * np.minimum(rin, rout)
    return fn


def _plan(seg, speed: float):
    """(duration, bank function, flight-path target in rad, flight-path transition time) of a segment."""
    gamma_transition = 5.0
    if isinstance(seg, Straight | Climb):
        duration = check_positive(seg.duration_s, f"{type(seg).__name__}.duration_s")
        fp = float(seg.flight_path_deg)
        if not (math.isfinite(fp) and abs(fp) < 45.0):
            raise FilterError(f"flight_path_deg must be within ±45°, got {seg.flight_path_deg!r}")
        return duration, (lambda tau: np.zeros_like(tau)), math.radians(fp), min(gamma_transition, duration)
    if isinstance(seg, Orbit):
        duration = check_positive(seg.duration_s, "Orbit.duration_s")
        bank = math.radians(_bank(seg.bank_deg))
        roll = float(seg.roll_time_s)
        if roll < 0 or 2 * roll > duration:
            raise FilterError(f"Orbit roll_time_s must be in [0, duration/2], got {seg.roll_time_s!r}")
        return duration, _roll_profile(bank, roll, duration), 0.0, min(gamma_transition, duration)
    if isinstance(seg, Turn):
        change = float(seg.heading_change_deg)
        if not math.isfinite(change) or change == 0.0:
            raise FilterError(f"Turn.heading_change_deg must be a non-zero number, got {seg.heading_change_deg!r}")
        bank_mag = abs(_bank(seg.bank_deg))
        if bank_mag == 0.0:
            raise FilterError("Turn.bank_deg must be non-zero")
        roll = float(seg.roll_time_s)
        if not (math.isfinite(roll) and roll >= 0):
            raise FilterError(f"Turn.roll_time_s must be ≥ 0, got {seg.roll_time_s!r}")
        bank = math.copysign(math.radians(bank_mag), change)
        full_rate = G0 * math.tan(abs(bank)) / speed
        # heading change during one roll-in (= one roll-out), by quadrature of g tan(φ(t)) / V
        x = np.linspace(0.0, 1.0, 2001)
        per_roll = float(np.trapezoid(G0 * np.tan(abs(bank) * smootherstep(x)) / speed, x * roll)) if roll else 0.0
        hold = (math.radians(abs(change)) - 2.0 * per_roll) / full_rate
        if hold < 0.0:
            raise FilterError(f"Turn of {change}° at {bank_mag}° bank is shorter than its roll-in and roll-out "
                             f"({math.degrees(2 * per_roll):.1f}°); use a larger heading change or shorter roll_time_s")
        duration = hold + 2.0 * roll
        return duration, _roll_profile(bank, roll, duration), 0.0, min(gamma_transition, duration)
    raise FilterError(f"unknown trajectory segment {seg!r}; use Straight, Climb, Turn or Orbit")
