"""The filter's prior: the INS's initial error σ (:class:`InitialErrors`), the nominal drawn from it, and the prior
σ and covariance of the filter's states (design notes §7)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from warptan.nav.frames import quat_exp, quat_mul
from warptan.nav.imu import ImuModel
from warptan.nav.ins import NavState


@dataclass(frozen=True)
class InitialErrors:
    """σ of the INS's initial error, drawn per seed; also the filter's prior (design notes §7 "high" defaults)."""

    pos_m: tuple[float, float, float] = (100.0, 100.0, 20.0)
    vel_mps: float = 0.5
    att_deg: tuple[float, float, float] = (0.1, 0.1, 0.5)


def initial_nominal(truth0: NavState, errors: InitialErrors, rng: np.random.Generator) -> NavState:
    """The INS's initial state: truth ⊖ e0 with e0 drawn from the σ of ``errors`` (true = nominal ⊕ e0)."""
    dp0 = rng.normal(0.0, errors.pos_m)
    dv0 = rng.normal(0.0, errors.vel_mps, 3)
    dth0 = rng.normal(0.0, np.radians(errors.att_deg))
    q = quat_mul(truth0.quat_nb, quat_exp(-dth0))
    return NavState(truth0.pos_n - dp0, truth0.vel_n - dv0, q / np.linalg.norm(q))


def prior_linear_sigma(errors: InitialErrors, grade) -> np.ndarray:
    """(12,) prior σ of [dv, dth, dba, dbg]: the initial velocity/attitude σ and the grade's turn-on bias σ."""
    return np.concatenate([np.full(3, errors.vel_mps), np.radians(errors.att_deg), np.full(3, grade.accel_bias),
                           np.full(3, grade.gyro_bias)])


def prior_sigma(errors: InitialErrors, grade) -> np.ndarray:
    """(15,) prior σ of [dp, dv, dth, dba, dbg]: the position σ, then :func:`prior_linear_sigma` (a flight log's
    ``initial.sigma``)."""
    return np.r_[np.asarray(errors.pos_m, dtype=np.float64), prior_linear_sigma(errors, grade)]


def prior_linear_cov(errors: InitialErrors, imu: ImuModel) -> np.ndarray:
    """P0 of [dv, dth, dba, dbg] (diagonal, :func:`prior_linear_sigma` squared)."""
    return np.diag(prior_linear_sigma(errors, imu.grade) ** 2)
