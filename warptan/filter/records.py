"""What the particle filter keeps and returns, and its small helpers: the particles on the device
(:class:`ParticleState`), one update's record (:class:`UpdateInfo`), the estimate (:class:`Estimate`), where an
interval's time goes (:class:`StepTimer`), the counter-based seeds of a launch (:func:`step_seed`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warptan.checks import FilterError, check_float32
from warptan.nav.ins import NavState

_MASK64 = (1 << 64) - 1


def step_seed_int(seed: int, counter: int, stream: int) -> int:
    """:func:`step_seed` of one seed in Python integers (the same 64-bit wrap-around)."""
    x = (seed * 0x9E3779B97F4A7C15 + counter * 0xBF58476D1CE4E5B9 + stream * 0x94D049BB133111EB) & _MASK64
    x ^= x >> 31
    x = (x * 0xD6E8FEB86659FD93) & _MASK64
    x ^= x >> 32
    return x & 0x7FFFFFFF


def step_seed(seed, counter: int, stream: int):
    """31-bit seeds for one kernel launch from filter seeds (int or array), a step counter and a stream id
    (splitmix64, vectorised; a few seeds in Python integers, the same values: NumPy's call cost 10 µs, twice an
    update)."""
    arr = np.asarray(seed)
    if arr.size <= 8 and arr.dtype.kind in "iu":
        if arr.ndim == 0:
            return step_seed_int(int(arr), int(counter), int(stream))
        return np.array([step_seed_int(int(v), int(counter), int(stream)) for v in arr.ravel()],
                        dtype=np.int64).reshape(arr.shape)
    with np.errstate(over="ignore"):
        x = (np.asarray(seed, dtype=np.uint64) * np.uint64(0x9E3779B97F4A7C15)
             + np.uint64(counter) * np.uint64(0xBF58476D1CE4E5B9) + np.uint64(stream) * np.uint64(0x94D049BB133111EB))
        x ^= x >> np.uint64(31)
        x *= np.uint64(0xD6E8FEB86659FD93)
        x ^= x >> np.uint64(32)
    out = (x & np.uint64(0x7FFFFFFF)).astype(np.int64)
    return int(out) if out.ndim == 0 else out


@dataclass
class ParticleState:
    """Particles on the device (B filters × n particles, filter-major)."""

    dp: wp.array
    """(N,) vec3 position errors, NED, m."""
    lin: wp.array
    """(N,) vec12 Kalman means [dv (m/s), dth (rad), dba (m/s²), dbg (rad/s)]."""
    logw: wp.array
    """(N,) float32 log-weights, normalised per filter."""


@dataclass
class UpdateInfo:
    """What one measurement update did to one filter (host values)."""

    ess: float
    """Effective sample size after the (last stage's) weight update, before resampling."""
    resampled: bool
    n_bad_loglik: int
    """Particles whose log-likelihood was NaN/inf (scored the floor)."""
    n_unpredictable: int
    """Particles that could predict no point of the measurement (off the map, nodata)."""
    all_points_invalid: bool
    """The measurement had no valid point: weights unchanged in effect."""
    respread: bool
    """The integrity monitor declared the filter lost: re-spread around the estimate."""
    stages: int = 1
    """Tempering stages applied."""
    skipped: bool = False
    """The update carried no usable information (no valid point, or the map does not cover the scan)."""
    applied: float = 1.0
    """Exponent of the likelihood applied (1 unless skipped or capped at ``max_stages``)."""
    nis: float = float("nan")
    """Smallest normalised squared residual of any particle (≈ 1 when a particle is at the truth and σ is
    right; the integrity monitor's input)."""


@dataclass
class Estimate:
    """The open-loop corrected navigation solution and its uncertainty (host, float64)."""

    nav: NavState
    """Nominal ⊕ estimated error (biases included)."""
    dp: np.ndarray
    """(3,) estimated position error, m."""
    lin: np.ndarray
    """(12,) estimated [dv, dth, dba, dbg]."""
    cov_pos: np.ndarray
    """(3, 3) covariance of the position estimate (particle spread), m²."""
    cov_lin: np.ndarray
    """(12, 12) mixture covariance of the linear part: P + spread of the particle means."""

    @property
    def sigma3_pos(self) -> np.ndarray:
        """(3,) 3σ bounds of the position estimate, m."""
        return 3.0 * np.sqrt(np.maximum(np.diag(self.cov_pos), 0.0))

    @property
    def sigma3_lin(self) -> np.ndarray:
        """(12,) 3σ bounds of [dv (m/s), dθ (rad), dba (m/s²), dbg (rad/s)]: the attitude and bias estimates'
        uncertainty."""
        return 3.0 * np.sqrt(np.maximum(np.diag(self.cov_lin), 0.0))


def _as_cov(value, n: int, name: str) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise FilterError(f"{name} must be {n} standard deviations or an {n}×{n} covariance, got {value!r}") from None
    if a.shape not in ((n,), (n, n)):
        raise FilterError(f"{name} must be {n} standard deviations or an {n}×{n} covariance, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise FilterError(f"{name} must be finite, got {a.tolist()}")
    if a.shape == (n,):
        if (a < 0).any():
            raise FilterError(f"{name}: standard deviations must be ≥ 0, got {a.tolist()}")
        a = np.diag(a**2)
    if np.any(np.linalg.eigvalsh(0.5 * (a + a.T)) < -1e-12):
        raise FilterError(f"{name} is not positive semi-definite")
    check_float32(np.sqrt(np.abs(np.diag(a))), f"{name} (its σ: the particles are float32)")
    return a


def _to_blocks(m: np.ndarray, k: int) -> np.ndarray:
    """(..., 3k, 3k) -> (..., k, k, 3, 3)."""
    lead = m.shape[:-2]
    return np.ascontiguousarray(m.reshape(*lead, k, 3, k, 3).swapaxes(-3, -2))


def _from_blocks(m: np.ndarray) -> np.ndarray:
    """(..., k, k, 3, 3) -> (..., 3k, 3k)."""
    lead, k = m.shape[:-4], m.shape[-4]
    return m.swapaxes(-3, -2).reshape(*lead, 3 * k, 3 * k)


def _imu_arrays(f_b, w_b) -> tuple[np.ndarray, np.ndarray]:
    """IMU specific force and body rate as float64 arrays, or a FilterError."""
    try:
        return np.asarray(f_b, dtype=np.float64), np.asarray(w_b, dtype=np.float64)
    except (TypeError, ValueError):
        raise FilterError(f"IMU samples must be numbers, got {f_b!r} and {w_b!r}") from None


class StepTimer:
    """Where the time of each measurement interval goes, from timers in :class:`MarginalizedParticleFilter` (set
    ``mpf.timer = StepTimer()``; None, the default, costs nothing). Per update, in ms:

    * ``host``: Python on the host — buffering the interval's IMU samples (:meth:`~MarginalizedParticleFilter.predict`),
      staging the interval, issuing the launches or the graph (CUDA; on the CPU the launches run as they are issued
      and count as device);
    * ``upload``: the model's ``stage`` — validating the measurement, packing it and copying it to the device (a
      host-to-device copy on CUDA, a copy into the particles' arrays on the CPU); the interval's IMU samples are
      copied inside the update's graph (device);
    * ``device``: the update's device work — CUDA: the time between two events around it on the stream (the IMU
      copies, INS and Riccati, moves, model, weights, resampling, record); CPU: the wall time of its launches.

    Device times on CUDA are read from their events when :meth:`times` is called (one synchronisation)."""

    def __init__(self):
        self.host_s: list[float] = []
        self.upload_s: list[float] = []
        self._device: list = []
        self._predict_s = 0.0

    def _add(self, host_s: float, upload_s: float, device) -> None:
        self.host_s.append(host_s + self._predict_s)
        self.upload_s.append(upload_s)
        self._device.append(device)
        self._predict_s = 0.0

    def times(self) -> dict[str, np.ndarray]:
        """``{"host": ..., "upload": ..., "device": ...}``, one value in ms per timed update."""
        device = [1e3 * d if isinstance(d, float) else wp.get_event_elapsed_time(*d) for d in self._device]
        return {"host": 1e3 * np.asarray(self.host_s), "upload": 1e3 * np.asarray(self.upload_s),
                "device": np.asarray(device, dtype=np.float64)}
