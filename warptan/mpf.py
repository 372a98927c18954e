"""The marginalized particle filter on the device, open-loop INS correction (SPEC §6; paper §IV).

Nonlinear state ``s^n = dp`` (3, N particles on the device); linear state ``s^l = [dv, dth, dba, dbg]``
(12), one Kalman mean per particle on the device and one shared 12×12 covariance ``P`` on the host
(float64): ``A^n``, ``A^l`` and ``Q`` do not depend on the particle, so neither does ``P``. Per IMU step
(``predict``) the host runs the Riccati recursion once (``N_k``, ``L_k``, ``P``) and one kernel moves every
particle; per measurement (``update``) the model scores every particle, weights are updated in log
space and normalised by log-sum-exp on the device, and the particles are resampled (ancestor indices,
systematic by default) when ``ESS < threshold · N``. Host work per step does not depend on N.

``A^n`` and ``A^l`` are blocks of the INS error transition of :func:`warptan.ins.error_transition`
(exact Jacobian: ``A^n = [dt I, 0.5 dt² (-R[a]x), 0.5 dt² (-R), 0]``; SPEC's ``[dt I, 0]`` plus the
O(dt²) terms). ``Q^n`` is a small position random walk (roughening, ``pos_noise`` m/√s).

The INS runs open loop: the output is nominal ⊕ estimated error, with the mixture covariance (Kalman
``P`` plus the spread of the particles). Trouble is recovered and counted, never returned as NaN: a
non-finite log-likelihood scores the floor; a scan no particle can predict (every particle off the map)
re-spreads the particles around the estimate with the prior spread.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warptan.device import resolve_device
from warptan.frames import quat_exp, quat_mul
from warptan.imu import ImuGrade, check_rate, imu_grade
from warptan.ins import Ins, NavState, error_transition, process_noise
from warptan.kernels import mpf as kmpf
from warptan.parallel import launch_rows, rows_of

SCHEMES = {"systematic": 0, "stratified": 1, "multinomial": 2}


def _resampler(scheme: int):
    def resample(cdf: wp.array, seed: int, ancestors_out: wp.array) -> wp.array:
        """Ancestor indices (N,) int32 from the inclusive cumulative weights ``cdf`` (N,) float32."""
        wp.launch(kmpf.ancestors_kernel, dim=cdf.shape[0], inputs=[int(seed), scheme, cdf],
                  outputs=[ancestors_out], device=cdf.device)
        return ancestors_out
    return resample


RESAMPLERS = {name: _resampler(code) for name, code in SCHEMES.items()}
"""name -> ``resample(cdf, seed, ancestors_out)``: systematic (one uniform), stratified (one per slot),
multinomial (independent draws)."""


def step_seed(seed: int, counter: int, stream: int) -> int:
    """A 31-bit seed for one kernel launch from the filter seed, a step counter and a stream id (splitmix)."""
    x = (seed * 0x9E3779B97F4A7C15 + counter * 0xBF58476D1CE4E5B9 + stream * 0x94D049BB133111EB) % (1 << 64)
    x ^= x >> 31
    x = (x * 0xD6E8FEB86659FD93) % (1 << 64)
    x ^= x >> 32
    return int(x & 0x7FFFFFFF)


@dataclass
class ParticleState:
    """Particles on the device."""

    dp: wp.array
    """(N,) vec3 position errors, NED, m."""
    lin: wp.array
    """(N,) vec12 Kalman means [dv (m/s), dth (rad), dba (m/s²), dbg (rad/s)]."""
    logw: wp.array
    """(N,) float32 normalised log-weights."""


@dataclass
class UpdateInfo:
    """What one measurement update did (host values)."""

    ess: float
    """Effective sample size after the weight update (before resampling)."""
    resampled: bool
    n_bad_loglik: int
    """Particles whose log-likelihood was NaN/inf (scored the floor)."""
    n_unpredictable: int
    """Particles that could predict no point of the measurement (off the map, nodata)."""
    all_points_invalid: bool
    """The measurement had no valid point: weights unchanged in effect."""
    respread: bool
    """Every particle was unpredictable: re-spread around the estimate with the prior spread."""


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


def _as_cov(value, n: int, name: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.shape == (n,):
        a = np.diag(a**2)
    if a.shape != (n, n) or not np.isfinite(a).all():
        raise ValueError(f"{name} must be {n} standard deviations or an {n}×{n} covariance, got shape {a.shape}")
    if np.any(np.linalg.eigvalsh(0.5 * (a + a.T)) < -1e-12):
        raise ValueError(f"{name} is not positive semi-definite")
    return a


class MarginalizedParticleFilter:
    """MPF over the INS error; see the module docstring.

    Args:
        model: A measurement model (:mod:`warptan.measurement`) whose ``evaluate(pos, quat, measurement)``
            scores particle poses.
        nominal: Initial nominal INS state (the INS's own belief).
        grade: IMU grade (process noise of the Kalman part).
        rate_hz: IMU rate, Hz.
        p0_pos: Prior of the position error: 3 σ (m) or a 3×3 covariance.
        p0_lin: Prior covariance of [dv, dth, dba, dbg]: 12 σ or a 12×12 covariance.
        n_particles: N.
        device: Warp device of the particles.
        seed: Seed of the filter's random numbers (counter-based: seed + step).
        resample_threshold: Resample when ESS < threshold · N.
        resampler: "systematic", "stratified" or "multinomial".
        pos_noise: Roughening, a position random walk in m/√s (``Q^n = pos_noise² dt I``).
    """

    def __init__(self, model, nominal: NavState, grade: str | ImuGrade, rate_hz: float, p0_pos, p0_lin,
                 n_particles: int = 500, device=None, seed: int = 0, resample_threshold: float = 0.5,
                 resampler: str = "systematic", pos_noise: float = 0.5):
        if not (isinstance(n_particles, (int, np.integer)) and n_particles >= 1):
            raise ValueError(f"n_particles must be a positive integer, got {n_particles!r}")
        if resampler not in RESAMPLERS:
            raise ValueError(f"unknown resampler {resampler!r}; choose one of {', '.join(RESAMPLERS)}")
        if not 0.0 <= resample_threshold <= 1.0:
            raise ValueError(f"resample_threshold must be in [0, 1], got {resample_threshold!r}")
        if not (np.isfinite(pos_noise) and pos_noise >= 0):
            raise ValueError(f"pos_noise must be ≥ 0 m/√s, got {pos_noise!r}")
        self.model = model
        self.grade = imu_grade(grade)
        self.ins = Ins(nominal, check_rate(rate_hz))
        self.dt = self.ins.dt
        self.p0_pos = _as_cov(p0_pos, 3, "p0_pos")
        self.P = _as_cov(p0_lin, 12, "p0_lin").copy()
        self.n = int(n_particles)
        self.device = resolve_device(device)
        self.seed = int(seed)
        self.resample_threshold = float(resample_threshold)
        self.resample = RESAMPLERS[resampler]
        if pos_noise == 0 and not np.any(self.P[0:3, 0:3]):
            raise ValueError("pos_noise = 0 with a zero velocity prior makes N_k singular; give one of them")
        self.q_n = (pos_noise**2) * self.dt * np.eye(3)
        self.q_l = process_noise(self.grade, self.dt)[3:15, 3:15]
        self._pending: list = []
        self.n_imu_steps = 0
        self.n_updates = 0
        self.n_respreads = 0
        self._chol_p0 = wp.mat33(*np.linalg.cholesky(self.p0_pos + 1e-12 * np.eye(3)).ravel())
        d, n = self.device, self.n
        self.state = ParticleState(wp.empty(n, dtype=wp.vec3, device=d), wp.empty(n, dtype=kmpf.vec12, device=d),
                                   wp.empty(n, dtype=wp.float32, device=d))
        self._spare = ParticleState(wp.empty_like(self.state.dp), wp.empty_like(self.state.lin),
                                    wp.empty_like(self.state.logw))
        self._pos = wp.empty(n, dtype=wp.vec3, device=d)
        self._quat = wp.empty(n, dtype=wp.vec4, device=d)
        self._chunk_max = wp.empty(kmpf.N_CHUNKS, dtype=wp.float32, device=d)
        self._chunk_counts = wp.empty((kmpf.N_CHUNKS, 2), dtype=wp.int32, device=d)
        self._chunk_sums = wp.empty((kmpf.N_CHUNKS, 2), dtype=wp.float64, device=d)
        self._stats = wp.zeros(5, dtype=wp.float64, device=d)
        self._moments_partial = wp.empty((kmpf.N_CHUNKS, kmpf.N_MOMENTS), dtype=wp.float64, device=d)
        self._moments = wp.empty(kmpf.N_MOMENTS, dtype=wp.float64, device=d)
        self._weights = wp.empty(n, dtype=wp.float32, device=d)
        self._cdf = wp.empty(n, dtype=wp.float32, device=d)
        self._ancestors = wp.empty(n, dtype=wp.int32, device=d)
        wp.launch(kmpf.init_particles_kernel, dim=n, inputs=[step_seed(self.seed, 0, 0), self._chol_p0],
                  outputs=[self.state.dp, self.state.lin, self.state.logw], device=d)

    # ------------------------------------------------------------------ time update
    def predict(self, f_b, w_b) -> None:
        """One IMU sample: the nominal INS step and the shared Riccati recursion on the host; the particle
        moves are queued and run as one kernel launch before the next measurement or estimate."""
        nominal = self.ins.state
        F = error_transition(nominal, f_b, w_b, self.dt)  # validates the sample (NaN/inf raise)
        a_n, a_l = F[0:3, 3:15], F[3:15, 3:15]
        P = self.P
        pa = P @ a_n.T
        n_k = a_n @ pa + self.q_n
        n_k = 0.5 * (n_k + n_k.T)
        gain = np.linalg.solve(n_k, (a_l @ pa).T).T
        P = a_l @ P @ a_l.T + self.q_l - gain @ n_k @ gain.T
        self.P = 0.5 * (P + P.T)
        self.n_imu_steps += 1
        self._pending.append((step_seed(self.seed, self.n_imu_steps, 1), a_n, a_l, gain, np.linalg.cholesky(n_k)))
        self.ins.step(f_b, w_b)

    def flush(self) -> None:
        """Run the queued particle time updates (one launch for all of them)."""
        if not self._pending:
            return
        seeds, a_n, a_l, gain, chol = zip(*self._pending, strict=True)
        self._pending.clear()
        d = self.device
        mats = [wp.array(np.array(seeds, dtype=np.int32), dtype=wp.int32, device=d),
                wp.array(np.array(a_n, dtype=np.float32), dtype=kmpf.mat3x12, device=d),
                wp.array(np.array(a_l, dtype=np.float32), dtype=kmpf.mat12, device=d),
                wp.array(np.array(gain, dtype=np.float32), dtype=kmpf.mat12x3, device=d),
                wp.array(np.array(chol, dtype=np.float32), dtype=wp.mat33, device=d)]
        dp, lin = self.state.dp, self.state.lin
        launch_rows(kmpf.time_update_kernel, self.n,
                    lambda a, b: ([a or 0, *mats], [rows_of(dp, a, b), rows_of(lin, a, b)]), d,
                    row_cost=40 * len(seeds))

    # ------------------------------------------------------------------ measurement update
    def particle_poses(self) -> tuple[wp.array, wp.array]:
        """Each particle's hypothetical pose: (N,) vec3 positions and (N,) vec4 attitudes on the device."""
        self.flush()
        s = self.ins.state
        wp.launch(kmpf.particle_poses_kernel, dim=self.n,
                  inputs=[wp.vec3d(*s.pos_n), wp.vec4(*s.quat_nb), self.state.dp, self.state.lin],
                  outputs=[self._pos, self._quat], device=self.device)
        return self._pos, self._quat

    def update(self, measurement) -> UpdateInfo:
        """Weight the particles by ``measurement`` (taken at the current nominal time) and resample if needed."""
        pos, quat = self.particle_poses()
        out = self.model.evaluate(pos, quat, measurement)
        self.n_updates += 1
        d = self.device
        floor = -0.5 * self.model.likelihood.outlier_sigmas**2 * max(1, out.n_received)
        wp.launch(kmpf.add_loglik_partials_kernel, dim=kmpf.N_CHUNKS, inputs=[out.loglik, out.n_valid, float(floor)],
                  outputs=[self.state.logw, self._chunk_max, self._chunk_counts], device=d)
        wp.launch(kmpf.max_of_partials_kernel, dim=1, inputs=[self._chunk_max, self._chunk_counts],
                  outputs=[self._stats], device=d)
        wp.launch(kmpf.exp_partials_kernel, dim=kmpf.N_CHUNKS, inputs=[self.state.logw, self._stats],
                  outputs=[self._chunk_sums], device=d)
        wp.launch(kmpf.weight_stats_kernel, dim=1, inputs=[self._chunk_sums], outputs=[self._stats], device=d)
        wp.launch(kmpf.normalize_weights_kernel, dim=self.n, inputs=[self._stats], outputs=[self.state.logw],
                  device=d)
        stats = self._stats.numpy()  # the one host sync of an update: ESS and the counters
        n_unpredictable = int(stats[4])
        ess = float(stats[0])
        respread = out.n_received > 0 and n_unpredictable == self.n
        resampled = False
        if respread:
            self._respread()
        elif ess < self.resample_threshold * self.n:
            self._resample()
            resampled = True
        return UpdateInfo(ess=ess, resampled=resampled, n_bad_loglik=int(stats[2]), n_unpredictable=n_unpredictable,
                          all_points_invalid=out.all_points_invalid, respread=respread)

    def _resample(self) -> None:
        d = self.device
        wp.launch(kmpf.weights_from_log_kernel, dim=self.n, inputs=[self.state.logw], outputs=[self._weights],
                  device=d)
        wp.utils.array_scan(self._weights, self._cdf, inclusive=True)
        self.resample(self._cdf, step_seed(self.seed, self.n_updates, 2), self._ancestors)
        wp.launch(kmpf.gather_kernel, dim=self.n, inputs=[self._ancestors, self.state.dp, self.state.lin],
                  outputs=[self._spare.dp, self._spare.lin, self._spare.logw], device=d)
        self.state, self._spare = self._spare, self.state

    def _respread(self) -> None:
        """Lost (no particle can predict the scan): re-spread dp around the estimate with the prior spread."""
        centre = self.estimate().dp
        self.n_respreads += 1
        wp.launch(kmpf.respread_kernel, dim=self.n,
                  inputs=[step_seed(self.seed, self.n_updates, 3), wp.vec3(*centre), self._chol_p0],
                  outputs=[self.state.dp, self.state.logw], device=self.device)

    # ------------------------------------------------------------------ output
    def moments(self) -> np.ndarray:
        """Weighted moments of the particles (host float64):
        [Σw, Σw dp (3), Σw dp dpᵀ (9), Σw l (12), Σw l lᵀ (144)]."""
        self.flush()
        d = self.device
        wp.launch(kmpf.moment_partials_kernel, dim=kmpf.N_CHUNKS, inputs=[self.state.logw, self.state.dp,
                  self.state.lin], outputs=[self._moments_partial], device=d)
        wp.launch(kmpf.combine_partials_kernel, dim=kmpf.N_MOMENTS, inputs=[self._moments_partial],
                  outputs=[self._moments], device=d)
        return self._moments.numpy()

    def estimate(self) -> Estimate:
        """The corrected navigation solution, with the mixture covariance."""
        m = self.moments()
        total = m[0]
        if not (np.isfinite(m).all() and total > 0):
            raise FloatingPointError(f"particle moments are not finite (Σw = {total}); this is a bug")
        dp = m[1:4] / total
        cov_pos = m[4:13].reshape(3, 3) / total - np.outer(dp, dp)
        lin = m[13:25] / total
        spread = m[25:169].reshape(12, 12) / total - np.outer(lin, lin)
        cov_lin = self.P + 0.5 * (spread + spread.T)
        s = self.ins.state
        q = quat_mul(s.quat_nb, quat_exp(lin[3:6]))
        nav = NavState(s.pos_n + dp, s.vel_n + lin[0:3], q / np.linalg.norm(q), s.accel_bias + lin[6:9],
                       s.gyro_bias + lin[9:12])
        return Estimate(nav=nav, dp=dp, lin=lin, cov_pos=0.5 * (cov_pos + cov_pos.T), cov_lin=cov_lin)

