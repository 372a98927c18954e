"""IMU grades and the IMU error model (design notes §4; paper Table I after Groves, ch. 4).

A measured sample is ``ideal + bias + white noise``, the bias drawn at turn-on per axis from N(0, σ²)
and then walking: ``b_{k+1} = b_k + B sqrt(dt) n_k``. White noise from a density ``N`` has the discrete
standard deviation ``N / sqrt(dt)`` per sample. Units at this boundary are the datasheet's (mg, deg/h,
µg/√Hz, deg/√h); everything inside is SI.

Bias random walk is not in the paper's table. Our default moves each bias by 10 % of its turn-on σ per
hour (``B = 0.1 σ / sqrt(3600 s)``), a mild stand-in for bias instability; set it explicitly to change it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from warptan.checks import FilterError, check_positive, check_seed

G0 = 9.80665
"""Standard gravity, m/s² (also the unit of mg and µg)."""
DEG = math.pi / 180.0


@dataclass(frozen=True)
class ImuGrade:
    """Error parameters of an IMU grade, SI units.

    Attributes:
        name: Preset name.
        accel_bias: Turn-on accelerometer bias σ per axis, m/s².
        gyro_bias: Turn-on gyro bias σ per axis, rad/s.
        accel_noise: Accelerometer white-noise density, m/s²/√Hz.
        gyro_noise: Gyro white-noise density (angle random walk), rad/s/√Hz.
        accel_bias_walk: Accelerometer bias random-walk density, m/s³/√Hz.
        gyro_bias_walk: Gyro bias random-walk density, rad/s²/√Hz.
        accel_range: Largest plausible specific force magnitude per axis, m/s² (default 50 g): a sample beyond it
            is a fault, not a measurement (:meth:`warptan.filter.mpf.MarginalizedParticleFilter.predict`).
        gyro_range: Largest plausible body rate per axis, rad/s (default 20 rad/s, 1 150 °/s).
    """

    name: str
    accel_bias: float
    gyro_bias: float
    accel_noise: float
    gyro_noise: float
    accel_bias_walk: float
    gyro_bias_walk: float
    accel_range: float = 50.0 * G0
    gyro_range: float = 20.0

    @classmethod
    def from_datasheet(cls, name: str, accel_bias_mg: float, gyro_bias_deg_h: float, accel_noise_ug_rthz: float,
                       gyro_arw_deg_rth: float, walk_fraction_per_hour: float = 0.1) -> ImuGrade:
        """Build from datasheet units (mg, deg/h, µg/√Hz, deg/√h); bias walk as a fraction of σ per hour."""
        ab = accel_bias_mg * 1e-3 * G0
        gb = gyro_bias_deg_h * DEG / 3600.0
        return cls(name=name, accel_bias=ab, gyro_bias=gb, accel_noise=accel_noise_ug_rthz * 1e-6 * G0,
                   gyro_noise=gyro_arw_deg_rth * DEG / 60.0,
                   accel_bias_walk=walk_fraction_per_hour * ab / 60.0,
                   gyro_bias_walk=walk_fraction_per_hour * gb / 60.0)


IMU_GRADES: dict[str, ImuGrade] = {
    g.name: g for g in (
        ImuGrade.from_datasheet("consumer", 30.0, 300.0, 1000.0, 1.0),
        ImuGrade.from_datasheet("tactical_low", 10.0, 100.0, 200.0, 0.5),
        ImuGrade.from_datasheet("tactical", 1.0, 1.0, 100.0, 0.05),
        ImuGrade.from_datasheet("intermediate", 0.5, 0.1, 50.0, 0.01),
        ImuGrade.from_datasheet("navigation", 0.1, 0.01, 20.0, 0.002),
        ImuGrade.from_datasheet("marine", 0.01, 0.001, 10.0, 0.0005),
    )
}
"""The design notes §4 presets. The paper's "low-end tactical" is ``tactical_low``; "navigation/aviation" is
``navigation``."""


def imu_grade(name: str | ImuGrade) -> ImuGrade:
    """Look up a preset by name (an ImuGrade passes through)."""
    if isinstance(name, ImuGrade):
        return name
    if name not in IMU_GRADES:
        raise FilterError(f"unknown IMU grade {name!r}; choose one of {', '.join(IMU_GRADES)}")
    return IMU_GRADES[name]


def check_rate(rate_hz: float, name: str = "rate_hz") -> float:
    """A positive, finite rate in Hz."""
    return check_positive(rate_hz, name)


@dataclass
class ImuErrors:
    """One realisation of an IMU's errors: measured = ideal + bias(t) + noise.

    Attributes:
        accel_bias: (K, 3) accelerometer bias at each sample, m/s².
        gyro_bias: (K, 3) gyro bias at each sample, rad/s.
        accel_noise: (K, 3) accelerometer white noise, m/s².
        gyro_noise: (K, 3) gyro white noise, rad/s.
    """

    accel_bias: np.ndarray
    gyro_bias: np.ndarray
    accel_noise: np.ndarray
    gyro_noise: np.ndarray


class ImuModel:
    """Corrupts ideal IMU samples with a grade's errors, deterministically per seed.

    Args:
        grade: Preset name or :class:`ImuGrade`.
        rate_hz: Sample rate, Hz.
        seed: Random seed (one independent stream per seed).
        noise: False turns white noise off (biases stay).
        bias_walk: False turns the bias random walk off.
    """

    def __init__(self, grade: str | ImuGrade, rate_hz: float, seed: int = 0, noise: bool = True,
                 bias_walk: bool = True):
        self.grade = imu_grade(grade)
        self.rate_hz = check_rate(rate_hz)
        self.seed = check_seed(seed)
        if not noise:
            self.grade = replace(self.grade, accel_noise=0.0, gyro_noise=0.0)
        if not bias_walk:
            self.grade = replace(self.grade, accel_bias_walk=0.0, gyro_bias_walk=0.0)

    def errors(self, n_samples: int) -> ImuErrors:
        """Draw the error series for ``n_samples`` samples (same seed, same series)."""
        if n_samples < 0:
            raise FilterError(f"n_samples must be ≥ 0, got {n_samples}")
        g, dt = self.grade, 1.0 / self.rate_hz
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 0x1AB]))
        b_a0 = rng.normal(0.0, g.accel_bias, 3)
        b_g0 = rng.normal(0.0, g.gyro_bias, 3)
        walk_a = rng.normal(0.0, g.accel_bias_walk * math.sqrt(dt), (n_samples, 3))
        walk_g = rng.normal(0.0, g.gyro_bias_walk * math.sqrt(dt), (n_samples, 3))
        walk_a[0] = walk_g[0] = 0.0
        return ImuErrors(
            accel_bias=b_a0 + np.cumsum(walk_a, axis=0),
            gyro_bias=b_g0 + np.cumsum(walk_g, axis=0),
            accel_noise=rng.normal(0.0, g.accel_noise / math.sqrt(dt), (n_samples, 3)),
            gyro_noise=rng.normal(0.0, g.gyro_noise / math.sqrt(dt), (n_samples, 3)),
        )

    def corrupt(self, f_ideal, w_ideal) -> tuple[np.ndarray, np.ndarray, ImuErrors]:
        """Measured samples from ideal ones.

        Args:
            f_ideal: (K, 3) ideal specific force, body frame, m/s².
            w_ideal: (K, 3) ideal body rate, rad/s.

        Returns:
            (f_meas, w_meas, errors).
        """
        f = np.asarray(f_ideal, dtype=np.float64)
        w = np.asarray(w_ideal, dtype=np.float64)
        if f.shape != w.shape or f.ndim != 2 or f.shape[1] != 3:
            raise FilterError(f"ideal samples must be two (K, 3) arrays, got {f.shape} and {w.shape}")
        if not (np.isfinite(f).all() and np.isfinite(w).all()):
            raise FilterError("ideal IMU samples contain NaN or inf")
        e = self.errors(len(f))
        return f + e.accel_bias + e.accel_noise, w + e.gyro_bias + e.gyro_noise, e
