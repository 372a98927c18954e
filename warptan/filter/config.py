"""The particle filter's settings as one typed, validated object (:class:`FilterConfig`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from warptan.checks import FilterError

RESAMPLERS = ("systematic", "stratified", "multinomial")
"""Resampling schemes (ancestor indices from the cumulative weights): systematic (one uniform), stratified
(one per slot), multinomial (independent draws)."""
BAD_IMU_POLICIES = ("raise", "hold")
"""What :meth:`~warptan.filter.mpf.MarginalizedParticleFilter.predict` does with an implausible IMU sample."""
MIN_PARTICLES = 2
"""Fewest particles per filter: with one, no position is weighed against another (the filter is the INS)."""


@dataclass(frozen=True)
class FilterConfig:
    """Settings of a :class:`~warptan.filter.mpf.MarginalizedParticleFilter` (the defaults are the scenarios'
    unless a scenario file says otherwise). Validated when made: a :class:`~warptan.checks.FilterError` lists every
    problem at once. ``dataclasses.replace(config, field=value)`` or :meth:`with_` makes a changed copy."""

    n_particles: int = 500
    """Particles per filter, n (whole number ≥ 2; fewer than 10 warns: too few to represent the position error)."""
    resample_threshold: float = 0.5
    """Resample when ESS < threshold · n (in [0, 1])."""
    resampler: str = "systematic"
    """"systematic", "stratified" or "multinomial"."""
    pos_noise: float = 0.5
    """Roughening, a position random walk of the particles outside the Kalman part, m/√s (never enters N_k or L_k, so
    it is not read as velocity)."""
    kalman_pos_noise: float = 0.5
    """Position noise the Kalman part models (``Q^n = kalman_pos_noise² dt I`` in N_k, L_k), m/√s; the particles move
    with it too."""
    regularize: float = 1.0
    """Factor on the regularisation bandwidth ``h = regularize · (4 / (n (d + 2)))^(1/(d + 4))``, d = 3 (Silverman's
    rule; 0.39 at n = 500); 0 disables the jitter after resampling."""
    shrinkage: float = 0.5
    """Fraction of the kernel shrinkage in [0, 1]: the cloud's covariance grows by ``1 + (1 - shrinkage) h²`` per
    resampling (1: kept exactly), until its horizontal variance reaches the unaided INS's plus one prior's (the
    growth forgets what the map taught, never what the INS knows, with a margin for the acquisition:
    :func:`warptan.kernels.filter.weights.weight_stats`)."""
    temper_ess: float = 0.1
    """Tempering: each stage of an update applies the largest exponent that keeps ESS ≥ temper_ess · n (in [0, 1]; 0
    applies every update in one stage)."""
    max_stages: int = 8
    """Cap on the tempering stages of one update (integer in [1, 64]); exponent left at the cap is dropped."""
    max_unpredictable: float = 0.5
    """An update whose received points the particles cannot predict (off the map, nodata) in more than this weighted
    fraction is skipped (in [0, 1])."""
    integrity_window: int = 20
    """Informative updates the integrity statistic averages the smallest particle NIS over (integer in [1, 64])."""
    integrity_threshold: float = 9.0
    """Above it (after 2 · ``integrity_window`` informative updates) the filter is lost and re-spreads (> 0)."""
    respread_scale: float = 1.0
    """Re-spread covariance = respread_scale² · the position prior (≥ 0), about the estimate for half the particles;
    the other half about the unaided INS, that covariance grown to the INS's own variance where larger
    (:func:`warptan.kernels.filter.integrity.respread_particle`)."""
    measurement_update: bool = True
    """Kalman measurement update of the linear states from each particle's residuals (C ≠ 0, design notes §6b); False is
    the paper's filter (C = 0)."""
    closed_loop: bool = False
    """Inject the mean error into the nominal INS after every update the integrity monitor judges consistent."""
    gate_linear_update: bool = True
    """The Kalman measurement update of the linear states waits for the integrity monitor's verdict."""
    bad_imu: str = "raise"
    """An IMU sample that is not finite or beyond the grade's range: "raise" (a FilterError naming it) or "hold"
    (integrate the last good sample instead, counted)."""

    def __post_init__(self):
        problems = self.problems()
        if problems:
            raise FilterError("; ".join(problems))

    def problems(self) -> list[str]:
        """Every problem of these settings (empty: usable)."""
        out = []
        n = self.n_particles
        if not (isinstance(n, (int, np.integer)) and not isinstance(n, bool) and n >= MIN_PARTICLES):
            out.append(f"n_particles must be a whole number ≥ {MIN_PARTICLES} per filter (one particle cannot weigh "
                       f"one position against another), got {n!r}")
        if self.bad_imu not in BAD_IMU_POLICIES:
            out.append(f"bad_imu must be one of {', '.join(BAD_IMU_POLICIES)}, got {self.bad_imu!r}")
        if self.resampler not in RESAMPLERS:
            out.append(f"unknown resampler {self.resampler!r}; choose one of {', '.join(RESAMPLERS)}")
        for name in ("resample_threshold", "temper_ess", "shrinkage", "max_unpredictable"):
            value = getattr(self, name)
            if not (_number(value) and 0.0 <= value <= 1.0):
                out.append(f"{name} must be in [0, 1], got {value!r}")
        for name in ("pos_noise", "kalman_pos_noise", "regularize", "respread_scale"):
            value = getattr(self, name)
            if not (_number(value) and value >= 0):
                out.append(f"{name} must be a number ≥ 0, got {value!r}")
        for name in ("max_stages", "integrity_window"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and 1 <= value <= 64):
                out.append(f"{name} must be an integer in [1, 64], got {value!r}")
        if not (_number(self.integrity_threshold) and self.integrity_threshold > 0):
            out.append(f"integrity_threshold must be a positive number, got {self.integrity_threshold!r}")
        return out

    def with_(self, **changes) -> FilterConfig:
        """A copy with ``changes`` (field names; an unknown one is a :class:`~warptan.checks.FilterError` naming it
        and the fields)."""
        names = {f.name for f in dataclasses.fields(self)}
        unknown = sorted(set(changes) - names)
        if unknown:
            raise FilterError(f"unknown filter setting(s) {', '.join(unknown)}; FilterConfig has "
                              f"{', '.join(sorted(names))}")
        return dataclasses.replace(self, **changes)


def _number(value) -> bool:
    """A finite real number (not a bool)."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool) \
        and bool(np.isfinite(value))
