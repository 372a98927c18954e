"""Driving a filter through a simulated flight: truth → IMU and sensors → MPF → time series (design notes §6, §7).

``run_filter`` draws the INS's initial error from the prior σ (the filter's prior uses the same σ),
corrupts the ideal IMU samples with the grade's errors, runs the filter's time update at the IMU rate and
its measurement update at ``meas_rate_hz``, and records truth, INS-only, estimate, 3σ and ESS at every
measurement epoch. All randomness comes from ``seed``.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warptan.checks import FilterError
from warptan.filter.config import FilterConfig
from warptan.filter.mpf import MarginalizedParticleFilter
from warptan.filter.prior import InitialErrors, initial_nominal, prior_linear_cov
from warptan.kernels import mpf as kmpf
from warptan.nav.frames import quat_conj, quat_exp, quat_log, quat_mul
from warptan.nav.imu import ImuModel
from warptan.nav.ins import Ins
from warptan.nav.trajectory import Trajectory
from warptan.sensing.measurement import AltimeterModel
from warptan.sensing.sensors import AltimeterReading, Barometer, RadarAltimeter


@dataclass
class FilterRun:
    """Time series of one run, sampled at the measurement epochs (index 0 = the prior at t = 0)."""

    t_s: np.ndarray
    truth_pos: np.ndarray
    ins_pos: np.ndarray
    est_pos: np.ndarray
    sigma3_pos: np.ndarray
    ess: np.ndarray
    resampled: np.ndarray
    n_unpredictable: np.ndarray
    n_bad_loglik: np.ndarray
    respread: np.ndarray
    """Per epoch: the integrity monitor declared the filter lost and re-spread it."""
    all_points_invalid: np.ndarray
    stages: np.ndarray
    """Per epoch: tempering stages of the update."""
    nis: np.ndarray
    """Per epoch: smallest normalised squared residual of any particle (the integrity monitor's input)."""
    nis_avg: np.ndarray
    """Per epoch: its window mean, the integrity statistic."""
    skipped: np.ndarray
    """Per epoch: the update carried no usable information (map gap, no valid point)."""
    lin_err: np.ndarray
    """(T, 12) estimate minus truth of [velocity (m/s, NED), attitude (rad, body-frame rotation vector
    ``Log(q_true⁻¹ q_est)``), accelerometer bias (m/s²), gyro bias (rad/s)]."""
    sigma3_lin: np.ndarray
    """(T, 12) their reported 3σ (Kalman P plus the spread of the particles' Kalman means)."""
    update_time_s: np.ndarray
    """Host wall time of each measurement update call, s (the whole update on the CPU; on CUDA the host part
    and the enqueue of the captured device work, which runs asynchronously)."""
    predict_time_s: float
    """Host wall time of all ``predict`` calls together (buffering the IMU samples), s."""
    n_particles: int
    device: str
    info: dict = field(default_factory=dict)

    @property
    def error(self) -> np.ndarray:
        """(T, 3) estimate minus truth, NED, m."""
        return self.est_pos - self.truth_pos

    def _after(self, after_s: float) -> np.ndarray | None:
        """Epochs with ``t ≥ after_s`` (None when the run ended before)."""
        sel = self.t_s >= after_s
        return sel if sel.any() else None

    def _rms(self, err: np.ndarray, after_s: float) -> np.ndarray:
        sel = self._after(after_s)
        return np.full(err.shape[1], np.nan) if sel is None else np.sqrt(np.mean(err[sel] ** 2, axis=0))

    def _covered(self, err: np.ndarray, sigma3: np.ndarray, after_s: float) -> np.ndarray:
        sel = self._after(after_s)
        return np.full(err.shape[1], np.nan) if sel is None else np.mean(np.abs(err[sel]) <= sigma3[sel], axis=0)

    def rmse(self, after_s: float = 0.0) -> np.ndarray:
        """(3,) RMSE north, east, down of the estimate over ``t ≥ after_s``, m."""
        return self._rms(self.error, after_s)

    def coverage(self, after_s: float = 0.0) -> np.ndarray:
        """(3,) fraction of epochs where ``|error| ≤ 3σ``, per axis."""
        return self._covered(self.error, self.sigma3_pos, after_s)

    def lin_rmse(self, after_s: float = 0.0) -> np.ndarray:
        """(12,) RMSE of [velocity, attitude, accelerometer bias, gyro bias] over ``t ≥ after_s`` (SI units)."""
        return self._rms(self.lin_err, after_s)

    def lin_coverage(self, after_s: float = 0.0) -> np.ndarray:
        """(12,) fraction of epochs where the linear states' ``|error| ≤ 3σ``."""
        return self._covered(self.lin_err, self.sigma3_lin, after_s)


def run_filter(truth: Trajectory, terrain_map, model, imu: ImuModel | Sequence[ImuModel], sensor=None, *,
               terrain_truth=None, baro: Barometer | None = None, config: FilterConfig | None = None,
               device=None, seed: int | Sequence[int] = 0, meas_rate_hz: float = 10.0,
               initial: InitialErrors | None = None, progress=None, record: dict | None = None,
               **settings) -> FilterRun | list[FilterRun]:
    """Run one filter over a simulated flight — or a batch of independent runs (one per seed) in one filter.

    Args:
        truth: The true trajectory (IMU rate = its rate).
        terrain_map: The DEM the filter predicts with (the model's terrain).
        model: A measurement model built on ``terrain_map``.
        imu: IMU error model (grade, rate, seed of the IMU errors); a list of them for a batch.
        sensor: A :class:`~warptan.sensing.sensors.PointCloudSensor` for point-cloud models, or a
            :class:`~warptan.sensing.sensors.RadarAltimeter` (default) for the altimeter model.
        terrain_truth: The terrain the sensor sees (default: the map).
        baro: Barometer for the altimeter model (default σ = 1 m).
        device: Warp device of the particles.
        seed: Seed of a run (initial error, sensor noise, filter); a list of seeds runs a batch: every run
            has its own INS, IMU errors, measurements and particles, and they share every kernel launch.
        meas_rate_hz: Measurement rate; a divisor of the IMU rate (``--paper-rates``: equal to it).
        initial: Initial-error σ (drawn for the INS and used as the prior).
        progress: Optional callable(k, n_steps) called at every measurement epoch.
        record: A dict to fill with what the filter received (for a flight log, :mod:`warptan.io.flightlog`):
            ``f``, ``w`` (K, B, 3) IMU samples, ``epochs`` (IMU sample index of each update), ``measurements``
            (per update, the B measurements), ``nominal0`` (B initial INS states), ``true_bias`` (B × (K, 6)).
        config: The filter's settings (:class:`~warptan.filter.config.FilterConfig`; default its defaults).
        **settings: Fields of ``config`` changed (e.g. ``n_particles=1000``), as
            :class:`~warptan.filter.mpf.MarginalizedParticleFilter` takes them.

    Returns:
        A :class:`FilterRun`, or a list of them (one per seed) for a batch.
    """
    batched = isinstance(seed, (list, tuple, np.ndarray))
    seeds = [int(s) for s in (seed if batched else [seed])]
    imus = list(imu) if isinstance(imu, (list, tuple)) else [imu] * len(seeds)
    if len(imus) != len(seeds):
        raise FilterError(f"{len(seeds)} seeds need {len(seeds)} IMU models (or one), got {len(imus)}")
    initial = initial or InitialErrors()
    terrain_truth = terrain_truth or terrain_map
    for m in imus:
        if abs(m.rate_hz - truth.rate_hz) > 1e-9:
            raise FilterError(f"IMU rate {m.rate_hz} Hz differs from the trajectory's {truth.rate_hz} Hz")
    decim = truth.rate_hz / meas_rate_hz
    if meas_rate_hz <= 0 or abs(decim - round(decim)) > 1e-9:
        raise FilterError(f"measurement rate {meas_rate_hz} Hz must divide the IMU rate {truth.rate_hz} Hz")
    decim = round(decim)
    altimeter = isinstance(model, AltimeterModel)
    if altimeter:
        sensor = sensor or RadarAltimeter()
        baro = baro or Barometer()
    elif sensor is None:
        raise FilterError("a point-cloud model needs a PointCloudSensor")
    rngs = [np.random.default_rng(np.random.SeedSequence([s, 0x7A4])) for s in seeds]
    nominal0 = [initial_nominal(truth.state(0), initial, rng) for rng in rngs]
    corrupted = [m.corrupt(truth.f_b, truth.w_b) for m in imus]
    true_bias = [np.hstack([c[2].accel_bias, c[2].gyro_bias]) for c in corrupted]  # (K, 6) per run
    f_meas = np.stack([c[0] for c in corrupted], axis=1)  # (K, B, 3)
    w_meas = np.stack([c[1] for c in corrupted], axis=1)
    ins_only = [Ins(nominal0[b], truth.rate_hz).run(f_meas[:, b], w_meas[:, b])["pos_n"] for b in range(len(seeds))]
    mpf = MarginalizedParticleFilter(model, nominal0 if batched else nominal0[0], imus[0].grade, truth.rate_hz,
                                     np.asarray(initial.pos_m), prior_linear_cov(initial, imus[0]),
                                     config, device=device, seed=seeds if batched else seeds[0], **settings)
    n_steps = len(truth.f_b)
    epochs = [0, *range(decim, n_steps + 1, decim)]
    prior = mpf.estimate()
    received, update_time = [], []
    predict_time = 0.0
    k = 0
    for epoch in epochs[1:]:
        t0 = time.perf_counter()
        mpf.predict_many(f_meas[k:epoch] if batched else f_meas[k:epoch, 0],
                         w_meas[k:epoch] if batched else w_meas[k:epoch, 0])
        k = epoch
        predict_time += time.perf_counter() - t0
        p_true, q_true = truth.pos_n[k], truth.quat_nb[k]
        if altimeter:
            meas = [AltimeterReading(sensor.measure(terrain_truth, p_true, rng), baro.measure(p_true, rng))
                    for rng in rngs]
        else:
            meas = sensor.measure_many(terrain_truth, p_true, q_true, rngs, device=mpf.device)
        if record is not None:
            record.setdefault("measurements", []).append(meas)
        t0 = time.perf_counter()
        mpf.update(meas if batched else meas[0], sync=False)
        update_time.append(time.perf_counter() - t0)
        received.append(mpf.last_n_received)
        if progress is not None:
            progress(k, n_steps)
    if record is not None:
        record.update(f=f_meas, w=w_meas, epochs=epochs[1:], nominal0=nominal0, true_bias=true_bias)
    idx = np.array(epochs)
    truth_at = {"pos": truth.pos_n[idx], "vel": truth.vel_n[idx], "quat": truth.quat_nb[idx]}
    k_bias = np.minimum(idx, n_steps - 1)
    return collect_runs(mpf, truth.t_s[idx], truth_at, [tb[k_bias] for tb in true_bias],
                        [ins[idx] for ins in ins_only], prior, received, update_time, predict_time, batched,
                        {"imu_steps": n_steps, "meas_rate_hz": meas_rate_hz})


def collect_runs(mpf: MarginalizedParticleFilter, t_s: np.ndarray, truth: dict | None, true_bias: list | None,
                 ins_pos: list, prior, received: list, update_time: list, predict_time: float, batched: bool,
                 info: dict) -> FilterRun | list[FilterRun]:
    """The :class:`FilterRun` of each filter from its device history (the one read-back of a run).

    Args:
        t_s: (T,) epoch times (the prior, then one per update).
        truth: ``pos``, ``vel``, ``quat`` (T, ·) at the epochs, or None (a recorded flight without truth: errors NaN).
        true_bias: Per filter (T, 6) true accelerometer and gyro biases at the epochs, or None.
        ins_pos: Per filter (T, 3) INS-only positions at the epochs.
        prior: The filters' estimates before the first update (``mpf.estimate()``; a list when batched).
    """
    wp.synchronize_device(mpf.device)
    hist = mpf.history()  # (T, B, N_SUMMARY): the one read-back of the run
    nominal_hist, p_diag = mpf.nominal_history(), mpf.covariance_history()
    n_epochs = len(t_s)
    if truth is None:
        truth = {"pos": np.full((n_epochs, 3), np.nan), "vel": np.full((n_epochs, 3), np.nan),
                 "quat": np.full((n_epochs, 4), np.nan)}
    prior = prior if batched else [prior]
    n_particles = mpf.n
    runs = []
    for b in range(mpf.n_filters):
        h = hist[:, b]
        bias = np.full((n_epochs, 6), np.nan) if true_bias is None else true_bias[b]
        lin_err, sig_lin = _linear_errors(truth, bias, prior[b], nominal_hist[:, b],
                                          h[:, kmpf.H_MEAN_L:kmpf.H_MEAN_L + 12],
                                          p_diag[:, b] + h[:, kmpf.H_VAR_L:kmpf.H_VAR_L + 12])
        mean = h[:, kmpf.H_MEAN_DP:kmpf.H_MEAN_DP + 3]
        var = h[:, kmpf.H_COV_DP:kmpf.H_COV_DP + 3] + np.array([0.0, 0.0, mpf.map_offset_var])
        est = np.vstack([prior[b].nav.pos_n, nominal_hist[:, b, kmpf.NOM_POS:kmpf.NOM_POS + 3] + mean])
        sig = np.vstack([prior[b].sigma3_pos, 3.0 * np.sqrt(np.maximum(var, 0.0))])
        respread = h[:, kmpf.H_RESPREAD] > 0
        runs.append(FilterRun(
            t_s=np.asarray(t_s, dtype=np.float64), truth_pos=truth["pos"], ins_pos=ins_pos[b], est_pos=est,
            sigma3_pos=sig, ess=np.r_[float(n_particles), h[:, kmpf.H_ESS]],
            resampled=np.r_[False, h[:, kmpf.H_RESAMPLES] > 0],
            n_unpredictable=np.r_[0, h[:, kmpf.H_UNPREDICTABLE]].astype(int),
            n_bad_loglik=np.r_[0, h[:, kmpf.H_BAD]].astype(int), respread=np.r_[False, respread],
            all_points_invalid=np.r_[False, np.array(received).reshape(len(received), -1)[:, b] == 0],
            stages=np.r_[0, h[:, kmpf.H_STAGES]].astype(int), nis=np.r_[np.nan, h[:, kmpf.H_NIS]],
            nis_avg=np.r_[np.nan, h[:, kmpf.H_NIS_AVG]], skipped=np.r_[False, h[:, kmpf.H_SKIPPED] > 0],
            lin_err=lin_err, sigma3_lin=sig_lin,
            update_time_s=np.r_[0.0, update_time], predict_time_s=predict_time, n_particles=n_particles,
            device=mpf.device.alias,
            info={"respreads": int(respread.sum()), "skipped_updates": int((h[:, kmpf.H_SKIPPED] > 0).sum()),
                  **info, "batch": mpf.n_filters, "sigma_m": float(mpf.model.sigma_m),
                  "injections": int(mpf.n_injections[b]),
                  **({} if mpf.learner is None else {"map_error_prior_m": mpf.learner.prior_sigma_m,
                                                      "map_error_learned_m": mpf.learner.sigma_m,
                                                      "map_error_prior_corr_m": mpf.learner.prior_corr_m,
                                                      "map_error_learned_corr_m": mpf.learner.corr_m,
                                                      "map_white_prior_m": mpf.learner.white_prior_m,
                                                      "map_white_learned_m": mpf.learner.white_m,
                                                      "map_error_readings": mpf.learner.readings})},
        ))
    return runs if batched else runs[0]


def _linear_errors(truth: dict, true_bias: np.ndarray, prior, nominal: np.ndarray, mean_l: np.ndarray,
                   var_l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T, 12) estimate minus truth of [v, θ, b_a, b_g] at the epochs (``truth`` and ``true_bias`` there) and their
    3σ, from the prior and, per update, the nominal INS before any injection, the mean Kalman mean and its total
    variance."""
    nom = {k: nominal[:, o:o + n] for k, o, n in (("vel", kmpf.NOM_VEL, 3), ("quat", kmpf.NOM_QUAT, 4),
                                                    ("ba", kmpf.NOM_BA, 3), ("bg", kmpf.NOM_BG, 3))}
    vel = np.vstack([prior.nav.vel_n, nom["vel"] + mean_l[:, 0:3]])
    quat = np.vstack([prior.nav.quat_nb, quat_mul(nom["quat"], quat_exp(mean_l[:, 3:6]))])
    bias = np.vstack([np.r_[prior.nav.accel_bias, prior.nav.gyro_bias],
                      np.hstack([nom["ba"] + mean_l[:, 6:9], nom["bg"] + mean_l[:, 9:12]])])
    att = quat_log(quat_mul(quat_conj(truth["quat"]), quat / np.linalg.norm(quat, axis=1, keepdims=True)))
    err = np.hstack([vel - truth["vel"], att, bias - true_bias])
    sig = 3.0 * np.sqrt(np.maximum(np.vstack([np.diag(prior.cov_lin), var_l]), 0.0))
    return err, sig
