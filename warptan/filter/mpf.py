# Over 500 lines for now: the filter's construction (its device state, the Kalman part's noise, the map-error
# learner) and the update's host side (staging, the learner's readings) share that state; issue 69 (filter state as
# typed data) is where it gets split.
"""The marginalized particle filter on the device, open- or closed-loop INS correction (design notes
§6, §6b; paper §IV).

Nonlinear state ``s^n = dp`` (3, N particles on the device); linear state ``s^l = [dv, dth, dba, dbg]``
(12), one Kalman mean per particle and one shared 12×12 covariance ``P`` per filter (float64), all on the device:
``A^n``, ``A^l`` and ``Q`` do not depend on the particle, so the time update of ``P`` does not.

Measurement update of the linear states (C ≠ 0, design notes §6b; ``measurement_update``): the point cloud sees the
attitude. Every model returns, per particle, the information its residuals (at the particle's own pose, its dθ
applied) carry on dθ: ``Λ_i = Σ_j H_jᵀ H_j / σ_att²``, ``b_i = Σ_j H_jᵀ r_j / σ_att²`` (H_j the prediction's
Jacobian w.r.t. dθ; velocity and biases do not enter a prediction). In the tempering stage that applies the last of
the update's exponent each particle takes its own gain against the shared prior, ``l_i += P_:θ (I + Λ_i A)⁻¹ b_i``
(A = P_θθ; 3×3 work per particle whatever the number of points), before that stage's resampling (a resampled
particle carries its ancestor's updated mean; without jitter the order is immaterial, with it the "l | dp locally
constant" choice below applies); the weights are the marginal ``N(r_i; 0, H_i A H_iᵀ + R)`` (the likelihood kernels'
attitude marginal). The shared P is then updated once, on the device at the end of the update
(``covariance_update_kernel``), with the weighted mean information of the particles, ``P⁺ = P - P_:θ Λ̄ (I + A Λ̄)⁻¹
P_θ:`` (Λ̄ ≈ Λ at the weighted mean pose). Our choice is one shared P, not one per particle: a per-particle P needs
a 12×12 Riccati per particle and IMU sample on the device (its N_k and L_k would differ per particle), and the
shared P gives honest bounds once two things are right (H100, 20 seeds, ``results/paper/gaussian``, side by side
with the previous table in ``results/paper/compare_projection.md``). First, Λ_i and b_i are the part of the scan's
attitude information a position offset cannot explain (the Schur complement,
:attr:`warptan.sensing.likelihood.Likelihood.project_position`): a particle's position is only as good as the cloud
(~0.25 m) while a scan pins the attitude to ~1 cm of lever arm, so with the whole information each Kalman mean absorbed
its particle's position offset as attitude and resampling handed one lineage's absorbed offsets to every particle (S3
attitude coverage 53–75 %, σ/RMSE 0.4–0.5, one seed lost). Second, the update waits for the integrity monitor's verdict
(``gate_linear_update``): a scan read at a wrong position mode is fitted by a wrong attitude (S2 seed 11: 2.5° of yaw
in a 4 s false lock, a yaw-gyro error of 131 °/h a minute later). Now attitude 3σ coverage is 99–100 % in every
point-cloud scenario, mean σ/RMSE 0.99–1.5 (S8 yaw 1.52, S11 roll/yaw 1.73/1.70), attitude RMSE ≤ 0.0023° outside S2
(0.004/0.006/0.011°) and the flat-terrain yaw (0.02°), S2's gyro-bias error after 60 s 4.4/4.3/4.0 °/h. A per-particle
P was not built or measured.

Closed loop (``closed_loop``): after each update of a filter its integrity monitor has judged consistent, a kernel
at the end of the update injects the weighted mean error into the nominal INS (position, velocity, attitude ``q ⊗
Exp(θ̂)``, biases), every particle's error is reset relative to the new nominal on the device (its total state
unchanged, the attitude composed exactly), and ``P <- G P Gᵀ``, ``G = diag(I, I - [θ̂/2]×, I, I)`` (Solà 2017 §6.3).
Measured (H100, 20 seeds, all scenarios, ``results/closed_loop``): the same accuracy as open loop within the
intervals in 11 scenarios and one divergent seed in S12 (altimeter, flat terrain); the default is open loop.

The device program of an update (the nominal INS and Riccati interval, the particle moves, the tempering stages,
the record; graphs, recorded launches and the CUDA block forms) is :class:`warptan.filter.program.UpdateProgram`,
this class's base.

``A^n`` and ``A^l`` are blocks of the INS error transition of :func:`warptan.nav.ins.error_transition`
(exact Jacobian: ``A^n = [dt I, 0.5 dt² (-R[a]x), 0.5 dt² (-R), 0]``; the design notes' (§6) ``[dt I, 0]`` plus the
O(dt²) terms). ``Q^n`` (``kalman_pos_noise``) is the position noise the Kalman part models (in N_k and L_k);
roughening (``pos_noise``) is added to the particles' dp only, so L_k never reads it as velocity. Measured on
S8 (paper likelihood, 6 seeds): roughening outside with a small Kalman noise (0.05 m/√s) was worse (5.3/4.2 m)
than 0.5 m/√s in the Kalman part (2.5/1.7 m), which keeps the velocity uncertainty in P instead of collapsing
it into the particles; both default to 0.5 m/√s.

Jitter and the linear means: a jittered particle keeps its ancestor's Kalman mean ``l``. The kernel is a
smoothing of the dp marginal whose width (``h`` ≈ 0.4 of the cloud's spread) is well inside the scale on
which ``l | dp`` varies, i.e. ``l | dp`` is taken as locally constant over the kernel (our choice: a
regression of l on dp would add 36 cross-moments per filter for a shift of a fraction of a kernel width);
the shared ``P`` is untouched (the jitter does not inform ``l``).

A stated map error (``Likelihood.map_error_sigma_m``) whose offset under the scan the model's prediction cannot
tell from the aircraft's altitude (ray casts, sliding, the altimeter without a barometer: ``model.absorbs_map_offset``)
makes the particles' altitude the height above the map: the offset's variance ``var_b`` is added to the reported
altitude variance (``map_offset_var``; the estimate's ``cov_pos`` and the runs' σ) and its change along the track is
process noise on the down velocity, ``q_v = 4 σ_e² v³ / L³`` at each filter's nominal ground speed at construction
(:meth:`warptan.sensing.likelihood.Likelihood.offset_process`; per filter, as the fix wander below: a filter of a
batch is the filter run alone). A point-cloud model's fix of the horizontal position
wanders along the track with the error: ``Q^n`` grows by ``2 σ_e² v / ℓ``, ℓ the shorter of L and the terrain slope's
correlation length (:meth:`warptan.sensing.likelihood.Likelihood.fix_process`), or the Kalman part reads the wander as
velocity. Ground read again after the map-error modes forgot it weighs less: each update's exponent is what one more
pass adds to passes whose fixes are correlated by ρ (``(1 − ρ)/((1 + Cρ)(1 + (C − 1)ρ))`` after C passes; ρ = 0.9,
:class:`warptan.sensing.likelihood.RevisitMemory`), not 1.

Integrity (MBARI TRN style): every model returns each particle's normalised squared residual (NIS, mean of
``min((r/σ)², k_out²)`` over the received points; ≈ 1 at the true pose); the smallest NIS of any particle — is
there a hypothesis that explains the scan? — is averaged over the last ``integrity_window`` informative
updates (a wide but healthy cloud still holds such particles; the posterior-weighted NIS, which read a wide
cloud under a flat likelihood as lost, is only recorded). Above ``integrity_threshold`` the filter is lost: it
re-spreads around its estimate with ``respread_scale`` × the prior σ, and the record says so.

The output is nominal ⊕ estimated error, with the mixture covariance (Kalman ``P`` plus the spread of the
particles). Trouble is recovered and counted, never returned as NaN: a
non-finite log-likelihood scores the floor; an update with no valid point, or whose points the particles
mostly cannot predict (the map does not cover the scan: the aircraft, or the filter, is off the map), is
skipped — no information, so it cannot drag the estimate towards the map — and recorded as skipped.
"""

from __future__ import annotations

import math
import time
import warnings

import numpy as np
import warp as wp

from warptan.checks import FilterError, FilterWarning
from warptan.device import HostEcho, Uploads, resolve_device
from warptan.filter.config import RESAMPLERS, FilterConfig
from warptan.filter.intake import MAX_STEPS_PER_INTERVAL, ImuIntake
from warptan.filter.program import _STREAM_INIT
from warptan.filter.readout import Readout
from warptan.filter.records import (
    ParticleState,
    StepTimer,
    UpdateInfo,
    _as_cov,
    _to_blocks,
    step_seed,
)
from warptan.kernels import likelihood as klik
from warptan.kernels import mpf as kmpf
from warptan.kernels import nav as knav
from warptan.nav.imu import G0, ImuGrade, check_rate, imu_grade
from warptan.nav.ins import NavState, process_noise
from warptan.parallel import Recorder, launch
from warptan.sensing.learner import MapErrorLearner
from warptan.sensing.likelihood import RevisitMemory

SCHEMES = {name: k for k, name in enumerate(RESAMPLERS)}
"""The kernels' number of each resampling scheme (:data:`warptan.filter.config.RESAMPLERS`)."""
_SYM6_INDEX = np.array([[0, 3, 4], [3, 1, 5], [4, 5, 2]])
"""Entry of a symmetric 3×3 matrix stored as six columns (00 11 22 01 02 12, as the kernels write it)."""
FEW_PARTICLES = 10
"""Below this many particles per filter the filter warns (:class:`~warptan.checks.FilterWarning`): too few to
represent the position error; its estimate and bounds are not meaningful."""


class MarginalizedParticleFilter(ImuIntake, Readout):
    """MPF over the INS error; see the module docstring. One filter, or a batch of B independent filters
    (same model, IMU grade and prior; own nominal INS, seed, measurements) whose particles share one array.

    Args:
        model: A measurement model (:mod:`warptan.sensing.measurement`): ``stage(measurements, pos, quat)`` then
            ``launch(pos, quat) -> ModelOutput`` with per-particle log-likelihoods.
        nominal: Initial nominal INS state, or a list of B (a batch).
        grade: IMU grade (process noise of the Kalman part).
        rate_hz: IMU rate, Hz.
        p0_pos: Prior of the position error: 3 σ (m) or a 3×3 covariance.
        p0_lin: Prior covariance of [dv, dth, dba, dbg]: 12 σ or a 12×12 covariance.
        config: The filter's settings (:class:`~warptan.filter.config.FilterConfig`: particles, resampling,
            roughening, regularisation, tempering, integrity, Kalman measurement update, closed loop, IMU policy;
            units and ranges in its fields); default ``FilterConfig()``.
        device: Warp device of the particles.
        seed: Seed of the filter's random numbers (counter-based: seed + step), or B seeds.
        graph: Capture the device work of a measurement update (particle moves, poses, model, weights,
            resampling, record) once and replay it: True, False, or None = on CUDA only.
        **settings: :class:`~warptan.filter.config.FilterConfig` fields changed from ``config`` (a shorthand:
            ``MarginalizedParticleFilter(..., n_particles=1000, closed_loop=True)``); an unknown name is a
            :class:`~warptan.checks.FilterError`.
    """

    PLATFORM_EVERY = 10
    """Updates between two readings of the revisit memory (:class:`~warptan.sensing.likelihood.RevisitMemory`; each
    reading's ground stands for the scans since the last): 1 s at 10 Hz, 50-100 m of flight against an error
    correlated over hundreds of metres (reading the platform's pose back and the memory's sums at every update was a
    large part of a GPU update's host time; a reading took about 0.12 ms on an H200 host). The same as the model's
    geometry look (``MODES_CHECK_EVERY``): both read the one platform pose copied back for them."""

    def __init__(self, model, nominal, grade: str | ImuGrade, rate_hz: float, p0_pos, p0_lin,
                 config: FilterConfig | None = None, *, device=None, seed=0, graph: bool | None = None, **settings):
        if config is None:
            config = FilterConfig().with_(**settings) if settings else FilterConfig()
        elif not isinstance(config, FilterConfig):
            raise FilterError(f"config must be a FilterConfig, got {type(config).__name__}")
        elif settings:
            config = config.with_(**settings)
        self.config = config
        """The filter's settings (:class:`~warptan.filter.config.FilterConfig`)."""
        c = config
        if c.n_particles < FEW_PARTICLES:
            warnings.warn(f"n_particles = {c.n_particles}: too few particles to represent the position error; the "
                          f"estimate and its bounds are not meaningful (use ≥ {FEW_PARTICLES}; the scenarios use 500)",
                          FilterWarning, stacklevel=2)
        nominals = list(nominal) if isinstance(nominal, (list, tuple)) else [nominal]
        if not nominals or not all(isinstance(x, NavState) for x in nominals):
            raise FilterError("nominal must be a NavState or a non-empty list of NavStates")
        self.batched = isinstance(nominal, (list, tuple))
        self.n_filters = b = len(nominals)
        raw = np.atleast_1d(np.asarray(seed))
        if raw.dtype.kind not in "iu" or raw.ndim != 1 or (raw.size and (raw.min() < 0 or raw.max() > 2**63 - 1)):
            raise FilterError(f"seed must be a whole number in [0, 2**63) or a list of them, got {seed!r}")
        seeds = raw.astype(np.int64)
        if seeds.shape != (b,) and seeds.shape != (1,):
            raise FilterError(f"{b} filters need {b} seeds (or one), got {seeds.shape[0]}")
        self.seeds = np.broadcast_to(seeds, (b,)).copy()
        self.model = model
        self.grade = imu_grade(grade)
        self.dt = 1.0 / check_rate(rate_hz)
        self.p0_pos = _as_cov(p0_pos, 3, "p0_pos")
        p0 = _as_cov(p0_lin, 12, "p0_lin")
        self.n = int(c.n_particles)
        self.device = resolve_device(device)
        self.resample_threshold = float(c.resample_threshold)
        self.scheme = SCHEMES[c.resampler]
        if c.kalman_pos_noise == 0 and not np.any(p0[0:3, 0:3]):
            raise FilterError("kalman_pos_noise = 0 with a zero velocity prior makes N_k singular; give one of them")
        self.q_pos = (c.kalman_pos_noise**2) * self.dt
        self.q_rough = (c.pos_noise**2) * self.dt
        ql = np.diag(process_noise(self.grade, self.dt))[3:15]
        self._q_lin = wp.vec4d(ql[0], ql[3], ql[6], ql[9])
        # A stated map error's offset under the scan rides on the particles' altitude (height above the map):
        # its variance (m²) is added to the reported altitude variance, its change along the track is noise on the
        # down velocity (Likelihood.offset_process). The wander of a scan's fix along the track under a stated map
        # error is position noise of the Kalman part (Likelihood.fix_process). Both at each filter's own nominal
        # ground speed at construction: a filter of a batch is the filter run alone.
        self.map_offset_var = 0.0
        q_v = np.zeros(b)
        lk = getattr(model, "likelihood", None)
        speeds = [float(np.linalg.norm(x.vel_n[:2])) for x in nominals]
        if getattr(model, "absorbs_map_offset", False) and hasattr(lk, "offset_process"):
            self.map_offset_var = lk.offset_process(speeds[0])[0]
            q_v = np.array([lk.offset_process(v)[1] for v in speeds])
        self._q_vel_down = q_v * self.dt
        self._speeds, self._q_pos_base = speeds, self.q_pos
        if getattr(model, "fixes_per_scan", False) and hasattr(lk, "fix_process"):
            self.q_pos = self.q_pos + np.array([lk.fix_process(v) for v in speeds]) * self.dt
        self.q_pos = np.broadcast_to(np.asarray(self.q_pos, dtype=np.float64), (b,)).copy()
        """(B,) Q^n's diagonal per filter (m² per nominal step): the Kalman part's position noise and the fix wander."""
        self._q_dev = (wp.array(self.q_pos, dtype=wp.float64, device=self.device),
                       wp.array(self._q_vel_down, dtype=wp.float64, device=self.device))
        self.learner = None
        """The map error's RMS learned in flight (:class:`~warptan.sensing.learner.MapErrorLearner`) when the
        likelihood states an error to learn (``map_error_learn``) and the filter runs one flight (a batch shares one
        likelihood: its filters keep the statement)."""
        if getattr(lk, "models_map_error", False) and getattr(lk, "map_error_learn", False) and b == 1:
            terrain = getattr(model, "terrain", None)
            post = max(float(getattr(terrain, "dn", 0.0)), float(getattr(terrain, "de", 0.0)))
            length = lk.map_error_corr_m if callable(getattr(model, "mode_spectrum", None)) else None
            white = lk.map_sigma_m if lk.sigma_m is None else None  # (a σ of its own fixes the per-point σ)
            self.learner = MapErrorLearner(lk.map_error_sigma_m, ceiling=lk.map_error_confidence, prior_corr_m=length,
                                           min_corr_m=2.0 * post, white_prior_m=white,
                                           sensor_sigma_m=lk.sensor_sigma_m, mismatch_m=model.surface_mismatch_m())
            self._moments_out = wp.zeros((b, kmpf.MOMENTS_LEN), dtype=wp.float64, device=self.device)
            self._reads = wp.array(np.ones((1, klik.MAX_MODES), np.float32), dtype=klik.modes_vec, device=self.device)
            self._reads_host = np.ones(klik.MAX_MODES, np.float32)  # (the model's mode_reads on the device)
            self._proj_out = wp.zeros((b, kmpf.PROJ_LEN), dtype=wp.float64, device=self.device)
            self._proj_ref = wp.zeros(b, dtype=wp.float32, device=self.device)
            self._moments_echo = HostEcho([self._moments_out, self._proj_out])
        self._spectrum_read = None  # (the length's spectrum without the modes the learner does not read)
        self._platform_echo = None  # (the nominal's attitude and position for the map-error modes' scan geometry)
        self._learn_launches = None  # (the arrays and values a map-error reading's recorded launches hold)
        self.max_stages = int(c.max_stages)
        self.bandwidth = float(c.regularize) * (4.0 / (self.n * 5.0)) ** (1.0 / 7.0)
        """Regularisation bandwidth h (Silverman's rule for d = 3 times ``regularize``)."""
        params = kmpf.UpdateParams()
        params.resample_threshold = self.resample_threshold
        params.temper_ess = float(c.temper_ess)
        params.bandwidth = self.bandwidth
        params.shrinkage = float(c.shrinkage)
        params.max_unpredictable = float(c.max_unpredictable)
        params.integrity_window = int(c.integrity_window)
        params.integrity_threshold = float(c.integrity_threshold)
        params.gate_linear = int(bool(c.gate_linear_update))
        params.integrity_min_updates = 2 * int(c.integrity_window)
        chol_p0 = np.linalg.cholesky(self.p0_pos + 1e-12 * np.eye(3))
        params.respread_chol = wp.mat33(*(c.respread_scale * chol_p0).ravel())
        params.respread_ins = int(not getattr(model, "fixes_per_scan", False))
        params.free_var = wp.full(b, 3.0e38, dtype=wp.float32, device=self.device)  # (set at each update)
        self._free_terms = self._unaided_terms(p0)
        self._free_terms[-1] += self.CAP_MARGIN * float(np.trace(self.p0_pos[:2, :2]))
        self._kernel_chol = wp.array(np.broadcast_to(self.bandwidth * chol_p0, (b, 3, 3)).copy(), dtype=wp.mat33,
                                     device=self.device)
        """(B,) each filter's regularisation kernel factor (m): ``h · chol(P0)`` at the start and ``h ·`` the
        re-spread's after one, else the last resampling's (``h`` times the weighted cloud's factor, scaled by
        :data:`warptan.kernels.mpf.JITTER_NIS`); a model that scores a particle for its kernel reads it
        (``bind_particle_kernel``: the altimeter)."""
        self.params = params
        self.measurement_update = bool(c.measurement_update)
        self.closed_loop = bool(c.closed_loop)
        self._no_info: tuple[wp.array, wp.array] | None = None
        self._no_pos_info: wp.array | None = None
        self._no_mode_arrays: wp.array | None = None
        self.graph = self.device.is_cuda if graph is None else bool(graph)
        self._block_stages = True  # a stage and its resampling as one block per filter (same bits; program.py)
        # the update's head and tail fused, the stages' conditionals nested (same bits; the CPU runs it in
        # tests/test_mpf.py): on CUDA, where it measured faster (H100, S8 one filter: device 0.309 -> 0.273 ms)
        self._lean = self.device.is_cuda
        self._early = False  # this update's head was queued before its scan was staged (lean, see update)
        self._interval_first = True  # (lean: queue the head before staging the scan; False for an A/B)
        self._recorder = Recorder() if self.device.is_cpu and not self.graph else None
        """Eager CPU updates replay their fixed pieces from recorded launches (:class:`warptan.parallel.Recorder`);
        None launches every kernel anew (CUDA eager, or set to None to compare)."""
        self.bad_imu = c.bad_imu
        self.timer: StepTimer | None = None
        """A :class:`StepTimer` to record where each update's time goes, or None."""
        self.n_imu_held = np.zeros(b, dtype=np.int64)
        """Per filter: IMU samples replaced by the last good one (``bad_imu="hold"``)."""
        self._last_imu = np.full((b, 2, 3), np.nan)
        self._nominal_steps = np.full(MAX_STEPS_PER_INTERVAL, self.dt)
        self._nominal_steps.flags.writeable = False
        self.n_imu_steps = 0
        self.n_updates = 0
        self.last_n_received = np.zeros(b, dtype=np.int64)
        """Valid received points per filter in the last update."""
        self._k = 0
        self._chol_p0 = wp.mat33(*chol_p0.ravel())
        # ---- device, float64: nominal INS, P and the interval's Φ and chol(S) (kernels/nav.py)
        d = self.device
        cpu = wp.get_device("cpu")
        self._nav = {
            "pos": wp.array(np.array([x.pos_n for x in nominals]), dtype=wp.vec3d, device=d),
            "vel": wp.array(np.array([x.vel_n for x in nominals]), dtype=wp.vec3d, device=d),
            "quat": wp.array(np.array([x.quat_nb for x in nominals]), dtype=wp.vec4d, device=d),
            "ba": wp.array(np.array([x.accel_bias for x in nominals]), dtype=wp.vec3d, device=d),
            "bg": wp.array(np.array([x.gyro_bias for x in nominals]), dtype=wp.vec3d, device=d),
            "cov": wp.array(_to_blocks(np.broadcast_to(p0, (b, 12, 12)), 4), dtype=wp.mat33d, device=d),
        }
        self._scratch = [wp.zeros((b, 5, 5), dtype=wp.mat33d, device=d), wp.zeros((b, 5, 5), dtype=wp.mat33d, device=d),
                         wp.zeros((b, 15, 15), dtype=wp.float64, device=d)]
        # ---- host staging of an interval: the IMU samples [f, w] and [K, move seed, resample seed] per filter. On
        # CUDA two pinned sets, alternating: the update's graph copies one while the host fills the other (an event
        # per set says when the graph that read it is done).
        n_sets = 2 if d.is_cuda else 1
        self._imu_host = [wp.zeros((b, MAX_STEPS_PER_INTERVAL, 3), dtype=wp.vec3d, device=cpu, pinned=d.is_cuda)
                          for _ in range(n_sets)]
        self._ints_host = [wp.zeros((b, knav.N_INTS), dtype=wp.int32, device=cpu, pinned=d.is_cuda)
                           for _ in range(n_sets)]
        self._ints_np = [x.numpy() for x in self._ints_host]
        self._imu_rows = [x.numpy().transpose(1, 0, 2, 3) for x in self._imu_host]  # (sample, filter, [f, w, dt], 3)
        self._events = [wp.Event(device=d) for _ in range(n_sets)] if d.is_cuda else []
        self._staging_buffers = [{} for _ in range(n_sets)]  # the scan's pinned buffers per set (_stage_scan)
        self._set = 0
        self._imu = wp.empty_like(self._imu_host[0], device=d) if d.is_cuda else self._imu_host[0]
        self._ints = wp.zeros((b, knav.N_INTS), dtype=wp.int32, device=d) if d.is_cuda else self._ints_host[0]
        self._interval_k = 0
        self._ahead = 0  # this interval's samples that already ran (UpdateProgram._advance)
        self._run_ahead = self.graph and d.is_cuda  # predict_many runs its samples at once (the CUDA graph default)
        self._nav_progress = wp.zeros((b, 2), dtype=wp.float64, device=d)  # [samples done, steps] of the interval
        self._dev = {"phi": wp.zeros((b, 5, 5), dtype=wp.mat33, device=d),
                     "chol": wp.zeros((b, 5, 5), dtype=wp.mat33, device=d),
                     "pose": wp.array(np.array([np.r_[x.pos_n, x.quat_nb] for x in nominals]), dtype=wp.float64,
                                      device=d),
                     "seeds": self._ints[:, knav.INT_MOVE_SEED],
                     "resample_seeds": self._ints[:, knav.INT_RESAMPLE_SEED],
                     "att_cov": wp.zeros(b, dtype=wp.mat33, device=d),
                     "p_col": wp.zeros((b, 4), dtype=wp.mat33, device=d)}
        self._injections = wp.zeros(b, dtype=wp.int32, device=d)
        # ---- device: particles and work arrays
        nt = b * self.n
        self.state = ParticleState(wp.empty(nt, dtype=wp.vec3, device=d), wp.empty(nt, dtype=kmpf.vec12, device=d),
                                   wp.empty(nt, dtype=wp.float32, device=d))
        self._spare = ParticleState(wp.empty_like(self.state.dp), wp.empty_like(self.state.lin),
                                    wp.empty_like(self.state.logw))
        # map-error mode amplitudes (a stated map error: warptan.kernels.likelihood.mode_prior): per particle the
        # prior mean for the next scan, per filter the variances (negative: none yet); spares for resampling
        self._mode_mean = wp.zeros(nt, dtype=klik.modes_vec, device=d)
        self._mode_var = wp.full(b, klik.modes_vec(-1.0), dtype=klik.modes_vec, device=d)
        self._mode_spare = (wp.empty(nt, dtype=klik.modes_vec, device=d), wp.empty(nt, dtype=klik.modes_vec, device=d))
        self._out = None
        self._pos = wp.empty(nt, dtype=wp.vec3, device=d)
        self._quat = wp.empty(nt, dtype=wp.vec4, device=d)
        self._chunk_max = wp.empty((b, kmpf.N_CHUNKS), dtype=wp.float32, device=d)
        self._chunk_min_nis = wp.empty((b, kmpf.N_CHUNKS), dtype=wp.float32, device=d)
        self._chunk_counts = wp.empty((b, kmpf.N_CHUNKS, 2), dtype=wp.int32, device=d)
        self._chunk_sums = wp.empty((b, kmpf.N_CHUNKS, kmpf.N_CHUNK_SUMS), dtype=wp.float64, device=d)
        self._summary_sums = wp.empty((b, kmpf.N_CHUNKS, kmpf.N_SUMMARY_SUMS), dtype=wp.float64, device=d)
        self._temper_partials = wp.empty((b, kmpf.N_CHUNKS, kmpf.N_TEMPER, 3), dtype=wp.float64, device=d)
        self._unpred_partials = wp.empty((b, kmpf.N_CHUNKS), dtype=wp.float64, device=d)
        self._temper_ess = wp.empty((b, kmpf.N_TEMPER), dtype=wp.float64, device=d)
        self._integrity = wp.zeros((b, kmpf.N_INTEGRITY), dtype=wp.float64, device=d)
        # the tempering stages' flags: more[s] = 1 when stage s runs (set on the device, cleared at the update's end)
        self._more_stages = wp.zeros(self.max_stages + 1, dtype=wp.int32, device=d)
        self._stage_flags = [self._more_stages[s:s + 1] for s in range(self.max_stages + 1)]
        self._cdf_sums = wp.empty((b, kmpf.N_CHUNKS), dtype=wp.float64, device=d)
        self._stats = wp.zeros((b, kmpf.N_STATS), dtype=wp.float64, device=d)
        self._exponent = wp.ones(b, dtype=wp.float32, device=d)  # per update (RevisitMemory)
        self._uploads = Uploads()  # (the exponent's and the learner's copies: pinned on CUDA, behind the device's work)
        self._exponent_host: np.ndarray | None = None  # (its value on the device: copied again only when it changes)
        self._revisits = None
        self._unread_scans = 0  # (updates since the revisit memory last read the platform's ground)
        self._moments_partial = wp.empty((b, kmpf.N_MOMENT_CHUNKS, kmpf.N_MOMENTS), dtype=wp.float64, device=d)
        # what estimate() reads, packed on the device and copied to the host at once (pinned memory on CUDA)
        self._readout = wp.empty((b, kmpf.N_READOUT), dtype=wp.float64, device=d)
        self._readout_host = (wp.empty((b, kmpf.N_READOUT), dtype=wp.float64, device="cpu", pinned=True)
                              if d.is_cuda else self._readout)
        self._readout_graph = None  # None: not run yet; then (record key, graph) once captured (CUDA graphs)
        self._cdf = wp.empty(nt, dtype=wp.float32, device=d)
        self._ancestors = wp.empty(nt, dtype=wp.int32, device=d)
        self._slot = wp.zeros(1, dtype=wp.int32, device=d)
        self._history = wp.zeros((256, b, kmpf.N_SUMMARY), dtype=wp.float64, device=d)
        self._nominal_hist = wp.zeros((256, b, kmpf.N_NOMINAL), dtype=wp.float64, device=d)
        self._p_hist = wp.zeros((256, b, 12), dtype=wp.float64, device=d)
        self._feedback = wp.zeros((b, kmpf.N_FEEDBACK), dtype=wp.float64, device=d)
        self._graphs: dict = {}
        self._graph_key = None
        self._generation = 0  # bumped when the filter replaces an array its recorded launches hold (history growth)
        init_seeds = wp.array(step_seed(self.seeds, 0, _STREAM_INIT).astype(np.int32), dtype=wp.int32, device=d)
        launch(kmpf.init_particles_kernel, dim=nt, inputs=[self.n, init_seeds, self._chol_p0],
                  outputs=[self.state.dp, self.state.lin, self.state.logw], device=d)

    # ------------------------------------------------------------------ time update: warptan.filter.intake
    # ------------------------------------------------------------------ measurement update
    def particle_poses(self) -> tuple[wp.array, wp.array]:
        """Each particle's hypothetical pose: (N,) vec3 positions and (N,) vec4 attitudes on the device."""
        self.flush()
        self._launch_poses()
        return self._pos, self._quat

    def update(self, measurement, sync: bool = True):
        """Weight the particles by ``measurement`` (a list of B for a batch; taken at the current nominal time)
        and resample / re-spread where needed. A measurement the model rejects raises before anything moves (on
        CUDA the interval and the particles' moves are queued once the model's ``check`` passed, to run while the
        scan is staged: a model whose ``stage`` refused it after that leaves the filter as after :meth:`flush`).

        Returns:
            :class:`UpdateInfo` (a list of B for a batch); with ``sync=False`` nothing (no host sync: the
            records are read later with :meth:`history`).
        """
        t_enter = time.perf_counter()
        if self.batched and not (isinstance(measurement, (list, tuple)) and len(measurement) == self.n_filters):
            raise FilterError(f"a batch of {self.n_filters} filters needs a list of {self.n_filters} measurements")
        attitude = None
        likelihood = getattr(self.model, "likelihood", None)
        map_modes = getattr(likelihood, "models_map_error", False)
        # lean (CUDA): the update's head (the interval, the particles' moves and poses) goes to the device once the
        # measurement is checked, and runs while the host stages the scan
        self._early = self._head_first()
        if self._early:
            self.model.check(measurement)  # a measurement refused here moves nothing
        revisit = False
        if map_modes:
            # the map-error modes' scan geometry needs the platform's attitude and the revisit memory its ground, each
            # every few updates (the model's MODES_CHECK_EVERY, PLATFORM_EVERY): the nominal as an earlier update left
            # it (copied to the host behind the device's work before an update that reads it, HostEcho: 1-2 s old at
            # 10 Hz, within the geometry's tolerance; on the CPU, and before two copies, the last interval's), so
            # neither waits for the head
            if self._platform_echo is None:
                self._platform_echo = HostEcho([self._nav["quat"], self._nav["pos"]])
            self._unread_scans += 1
            revisit = (self._unread_scans >= self.PLATFORM_EVERY or self._revisits is None
                       or self._revisits.likelihood.map_error_corr_m != likelihood.map_error_corr_m)
            if revisit or self.model.modes_look_due:
                quat, pos = self._platform_echo.read()
                attitude = quat[0]
            if self._early and revisit:  # the head reads the exponent
                self._read_again(likelihood, pos)
        if self._early:
            self._stage_interval()
            self._queue_head()
        out, staged = self._stage_scan(measurement, attitude)
        if revisit and not self._early:
            self._read_again(likelihood, pos)
        t_staged = time.perf_counter()
        if hasattr(self.model, "bind_attitude_cov"):
            self.model.bind_attitude_cov(self._dev["att_cov"])
        if hasattr(self.model, "bind_mode_state"):
            self.model.bind_mode_state(self._mode_mean, self._mode_var)
        if hasattr(self.model, "bind_particle_kernel"):
            self.model.bind_particle_kernel(self._kernel_chol)
        self._out = out
        self._ensure_history()
        if not self._early:
            self._stage_interval()
        self.n_updates += 1
        self._uploads.put("free_var", self.params.free_var,  # (the time flown: the IMU steps taken)
                          np.full(self.n_filters, np.polyval(self._free_terms, self.n_imu_steps * self.dt),
                                  dtype=np.float32))
        timer, events = self.timer, None
        if timer is not None and self.device.is_cuda:
            events = (wp.Event(self.device, enable_timing=True), wp.Event(self.device, enable_timing=True))
            wp.get_stream(self.device).record_event(events[0])
        t_queue = time.perf_counter()
        self._queue_update(out, staged)
        t_queued = time.perf_counter()
        if timer is not None:
            if events is not None:  # CUDA: issuing is host work, the device time is between the events
                wp.get_stream(self.device).record_event(events[1])
                timer._add(t_queued - t_staged, t_staged - t_enter, events)
            else:  # CPU: the launches ran as they were issued
                timer._add(t_queue - t_staged, t_staged - t_enter, t_queued - t_queue)
        self._next_set()
        if self.learner is not None and self.n_updates % self.learner.every == 0:
            self._learn_map_error()
        if map_modes and (self.model.modes_look_due or self._unread_scans + 1 >= self.PLATFORM_EVERY):
            self._platform_echo.queue()  # (what the next update reads)
        self.last_n_received = np.array(out.n_received)  # (after the device work is queued: nothing there reads it)
        return self._info(out) if sync else None

    CAP_MARGIN = 1.0
    """Priors' horizontal variance added to the unaided INS's where the regularisation's growth stops
    (:meth:`_unaided_terms`). At the unaided variance itself the first scans' cloud, as wide as the prior, could not
    grow into an acquisition's modes: over the flat tile (S10, nothing stated or told, 20-seed rows, CPU) one run
    in 60–180 locked onto a wrong mode at the first scan, 1–3 km off, whichever way the growth was held back (a
    stronger pull to the mean, 124c528, or a smaller jitter, 2181f14). With one prior of margin, 240 runs (S10
    learn and told over the ``long``, ``biased`` and ``short`` families, 40 seeds each) lost none, as before the
    cap; S12 over ``biased`` / ``long`` (20 seeds) 249 / 194 m at 91/94 and 100/98 % 3σ coverage, against 187 / 192
    m at the cap itself (the intervals ±41 / ±60 m)."""

    def _unaided_terms(self, p0: np.ndarray) -> np.ndarray:
        """The unaided INS's horizontal position error variance (m²) as a polynomial in the time flown t (numpy's
        order, highest power first), from the prior ``p0_pos``, ``p0_lin`` ([dv, dθ, db_a, db_g]) and the grade's
        accelerometer and gyro noise: ``tr P0 + tr P_v t² + VRW² t³ / 3 + (g² σ_tilt² + σ_ba²) t⁴ / 4 + g² ARW² t⁵ /
        10 + g² σ_bg² t⁶ / 36`` (the horizontal traces, VRW² and ARW² per axis; each error integrated once or twice
        into position, independent; the Schuler loop ignored: after tens of minutes the polynomial grows past the INS
        and caps nothing). Against the float64 propagation of the 15-state error model along a level straight flight
        it is within 1e-3 over 60 s and 1 % at 120 s for the navigation and the low tactical grade
        (``tests/test_mpf.py::test_the_unaided_variance_is_the_ins_error_models``; without the angle random walk
        term, left out before session 13, the low tactical grade's was 12 % short at 120 s). The regularisation's
        covariance growth stops there, plus :data:`CAP_MARGIN` priors (``UpdateParams.free_var``,
        :func:`warptan.kernels.filter.weights.weight_stats`)."""
        g = G0
        pos = float(np.trace(self.p0_pos[:2, :2]))
        vel = float(p0[0, 0] + p0[1, 1])
        tilt = float(p0[3, 3] + p0[4, 4])
        ba = float(p0[6, 6] + p0[7, 7])
        bg = float(p0[9, 9] + p0[10, 10])
        vrw = 2.0 * self.grade.accel_noise**2
        arw = 2.0 * self.grade.gyro_noise**2
        return np.array([g * g * bg / 36.0, g * g * arw / 20.0, (g * g * tilt + ba) / 4.0, vrw / 3.0, vel, 0.0, pos])

    def _learn_map_error(self) -> None:
        """A reading of the map-error evidence for :attr:`learner` (the modes' moments and, to learn the length, the
        residuals' raw projections on them: one copy to the host every ``learner.every`` updates; on CUDA the reading
        queued ``2 every`` updates before, :class:`HostEcho`: the host never waits for the device) and, when it moved,
        the error restated: the model's likelihood and mode table, the offset's vertical-velocity noise and the fix
        wander (in place: captured graphs read them; the offset's altitude variance keeps its level from
        construction, the statement's upper end)."""
        table = self._mode_table()
        if table is None or self._out is None:
            return
        m = table.shape[0] - klik.MODE_EXTRA_ROWS
        reads = self.model.mode_reads
        if not np.array_equal(reads, self._reads_host):
            self._uploads.put("reads", self._reads, reads[None])
            self._reads_host = reads
        spectrum = None
        projections = self.learner.log_len is not None or self.learner.white_var is not None
        lk = self.model.likelihood
        gate = lk.outlier_sigmas * math.sqrt(1.0 + (lk.map_error_sigma_m / self.model.sigma_m) ** 2)
        arrays = (table, self.state.logw, self.state.dp, self._out.nis, self._out.loglik, self._out.residual_m,
                  self._mode_mean, self._mode_var, self._quat, self.model.staged_cloud)
        scalars = (m, projections, float(self.model.sigma_m), float(gate), int(self.model.name == "raycast"))
        held = self._learn_launches
        if held is None or held[1] != scalars or any(a is not b for a, b in zip(held[0], arrays, strict=True)):
            held = self._learn_launches = (arrays, scalars, Recorder())  # (recorded again: an array or value moved)
        if projections:  # the raw projections on the modes and the energy outside them: the length's and the white
            # error's evidence
            self._proj_out.zero_()
        held[2].run(0, lambda: self._learn_launch(arrays, scalars))
        if projections and self.learner.log_len is not None:
            spectrum = self._read_spectrum(self.model.mode_spectrum(self.learner.LENGTH_FACTORS), reads)
        # (the spectrum of the table this reading reads, the per-point σ that whitened it)
        self._moments_echo.queue(tag=(spectrum, float(self.model.sigma_m)))
        moments, projections = self._moments_echo.read()
        spectrum, sigma = self._moments_echo.tag if self._moments_echo.tag is not None else (None, None)
        restated = self.learner.read(moments[0], projections[0], spectrum, sigma,
                                     getattr(self.model, "dropped_var_m2", 0.0))
        if restated is None:
            return
        self.model.restate_map_error(*restated)
        lk = self.model.likelihood
        if self._revisits is not None and self._revisits.likelihood.map_error_corr_m == lk.map_error_corr_m:
            self._revisits.likelihood = lk  # (a new length: restated at the next reading, _read_again)
        if getattr(self.model, "absorbs_map_offset", False):
            # the offset under the scan rides on the altitude: no scan sees it, so its variance stays as built (F times
            # the prior: a map 5 m high everywhere looks exact to the modes); its change along the track is the learned
            # level's
            self._q_vel_down = np.array([lk.offset_process(v)[1] for v in self._speeds]) * self.dt
        if getattr(self.model, "fixes_per_scan", False):
            q = self._q_pos_base + np.array([lk.fix_process(v) for v in self._speeds]) * self.dt
            self.q_pos = np.broadcast_to(np.asarray(q, dtype=np.float64), (self.n_filters,)).copy()
        self._uploads.put("q_pos", self._q_dev[0], self.q_pos)
        self._uploads.put("q_vel_down", self._q_dev[1], np.asarray(self._q_vel_down, dtype=np.float64))

    def _read_spectrum(self, spectrum: np.ndarray, reads: np.ndarray) -> np.ndarray:
        """``spectrum`` with the modes the learner does not read (``model.mode_reads``: mostly on points beyond 48°
        of the vertical) at zero, which the length's fit leaves out (the same array while both stay). The RMS was
        read from the modes near the vertical only, the length from all: on a banked scan (S5, S6) the grazing
        rays' modes, whose flat-ground sensitivity the spectrum assumes, drew the length away once a reading
        without a ruling mode read it too (since 999de27; S5's RMSE grew by about an eighth)."""
        key = (id(spectrum), reads.tobytes())
        if self._spectrum_read is None or self._spectrum_read[0] != key:
            mask = reads[: spectrum.shape[1]] > 0.5
            self._spectrum_read = (key, spectrum * mask[None, :], spectrum)  # (the source kept: its id stays its own)
        return self._spectrum_read[1]

    def _learn_launch(self, arrays: tuple, scalars: tuple) -> None:
        """The launches of a map-error reading (recorded once per set of arrays and values: ``_learn_map_error``):
        the modes' moments and, to learn the length and the white error, the residuals' raw projections on them."""
        table, logw, dp, nis, loglik, residual, mean, var, quat, cloud = arrays
        m, projections, sigma, gate, ray = scalars
        launch(kmpf.map_error_moments_kernel, dim=self.n_filters,
               inputs=[self.n, m, table, logw, dp, nis, mean, var, self._reads], outputs=[self._moments_out],
               device=self.device)
        if projections:
            launch(kmpf.loglik_max_kernel, dim=self.n_filters, inputs=[self.n, loglik], outputs=[self._proj_ref],
                   device=self.device)
            launch(kmpf.mode_projection_kernel, dim=self.n_filters * self.n,
                   inputs=[self.n, m, table, residual, loglik, self._proj_ref, sigma, gate, quat, cloud, ray],
                   outputs=[self._proj_out], device=self.device)

    def _read_again(self, likelihood, pos: np.ndarray) -> None:
        """The update's exponent over ground read again after the modes forgot it (:class:`RevisitMemory`), at the
        scan's footprint (the model's last) under the platform's position ``pos`` (B, 3), standing for the scans since
        the last reading."""
        if self._revisits is None:
            self._revisits = RevisitMemory(likelihood, self.n_filters)
        elif self._revisits.likelihood.map_error_corr_m != likelihood.map_error_corr_m:
            self._revisits.restate(likelihood)  # (a learned length: the passes flown stay in the memory)
        ground = pos[:, :2] + getattr(self.model, "footprint_centre", np.zeros(2))
        exponent = self._revisits.exponents(ground, scans=self._unread_scans).astype(np.float32)
        self._unread_scans = 0
        if self._exponent_host is None or not np.array_equal(exponent, self._exponent_host):  # (1 on fresh ground)
            self._uploads.put("exponent", self._exponent, exponent)
            self._exponent_host = exponent

    def _info(self, out):
        stats = self._stats.numpy()
        infos = [UpdateInfo(ess=float(s[kmpf.ST_ESS]), resampled=bool(s[kmpf.ST_RESAMPLES]),
                            n_bad_loglik=int(s[kmpf.ST_BAD]), n_unpredictable=int(s[kmpf.ST_UNPREDICTABLE]),
                            all_points_invalid=bool(out.n_received[b] == 0), respread=bool(s[kmpf.ST_RESPREAD]),
                            stages=int(s[kmpf.ST_STAGES]), skipped=bool(s[kmpf.ST_SKIP]),
                            applied=float(s[kmpf.ST_APPLIED]), nis=float(s[kmpf.ST_NIS_MIN]))
                 for b, s in enumerate(stats)]
        return infos if self.batched else infos[0]

    def _ensure_history(self) -> None:
        cap = self._history.shape[0]
        if self.n_updates < cap:
            return
        for name in ("_history", "_nominal_hist", "_p_hist"):
            old = getattr(self, name)
            bigger = wp.zeros((2 * cap, *old.shape[1:]), dtype=wp.float64, device=self.device)
            wp.copy(bigger, old, count=old.size)
            setattr(self, name, bigger)
        self._generation += 1

    def history(self) -> np.ndarray:
        """(updates, B, N_SUMMARY) record of every update so far (one host sync); columns
        :data:`warptan.kernels.mpf.H_ESS` … ``H_APPLIED``: ESS, resamplings, re-spread, bad log-likelihoods,
        unpredictable particles, Σw, mean dp (3, m) and its covariance (xx, yy, zz, xy, xz, yz, m²) after the
        update, tempering stages, smallest particle NIS, its window mean (the integrity statistic), skipped,
        exponent applied, posterior-weighted NIS, mean of the Kalman means l (12) and their spread's variance
        (12)."""
        return self._history.numpy()[: self.n_updates]

    def nominal_history(self) -> np.ndarray:
        """(updates, B, 16) the nominal INS at each measurement update, before any closed-loop injection:
        [p (3), v (3), q (4), b_a (3), b_g (3)] (one host sync)."""
        return self._nominal_hist.numpy()[: self.n_updates]

    def covariance_history(self) -> np.ndarray:
        """(updates, B, 12) the diagonal of the Kalman covariance P after each update's measurement update."""
        return self._p_hist.numpy()[: self.n_updates]

    @property
    def n_injections(self) -> np.ndarray:
        """Closed loop: injections into the nominal INS so far, per filter."""
        return self._injections.numpy().astype(np.int64)

    @property
    def n_respreads(self) -> int:
        """Re-spreads so far (all filters)."""
        return int(self.history()[:, :, kmpf.H_RESPREAD].sum())
