# Over 500 lines on purpose: the three models share one base (MeasurementModel: validation, staging, buffers, the
# map-error mode table, binding to the filter) and differ only in their launches; the likelihood's settings and its
# calibration are warptan.sensing.likelihood.
"""Measurement models: one log-likelihood per particle from its hypothetical pose (paper eqs. 14–17, design notes §5).

Each model takes the particles' poses on the device — positions (N,) vec3 NED in m and attitudes (N,)
vec4 [w, x, y, z] — and the received measurement, and gives every particle its log-likelihood with no
Python loop over particles or points:

* :class:`RaycastModel` — predicted ranges by ray casting (any backend), paper error of eq. 15; N×M threads
  fill the residuals, one thread per particle reduces them;
* :class:`SlidingModel` — the sliding grid, no ray cast, paper error of eq. 16; one fused kernel;
* :class:`AltimeterModel` — radar altimeter with barometric altitude, eq. 17.

The likelihood is the paper's Gaussian on the scalar error, or a per-point Gaussian / Student-t over
all valid residuals (:class:`Likelihood`, :mod:`warptan.kernels.likelihood` for the exact formulas).
The per-point scale is calibrated unless given: ``σ_eff² = σ_sensor² + n_corr σ_map²`` with ``σ_map`` the RMS
difference between the surface the model reads and the triangulated truth (bilinear vs triangles,
:attr:`~warptan.terrain.grid.Terrain.bilinear_mismatch_sigma_m`, 0 for ray casts, which read the triangles) plus
any known map error (``map_sigma_m``), and ``n_corr`` the updates over which a moving scan sees the same map
error (``map_correlation``). Every model also returns each particle's normalised squared residual
(the filter's integrity statistic).

Evaluation is two steps so that a filter step can be captured in a graph: :meth:`~MeasurementModel.stage`
copies the received measurement(s) into device buffers that the model keeps (host work O(M), not O(N)),
:meth:`~MeasurementModel.launch` only launches kernels on those buffers. ``evaluate`` does both. A batch of
B filters passes B measurements; its N = B·n particles are filter-major (particle i is filter ``i // n``).
"""

from __future__ import annotations

import dataclasses
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from warptan.checks import FilterError
from warptan.device import Uploads, one_blas_thread
from warptan.kernels import likelihood as klik
from warptan.kernels import raycast as kray
from warptan.kernels import simd as ksimd
from warptan.kernels import simd_ray as ksimd_ray
from warptan.kernels import sliding as kslide
from warptan.kernels.filter.resampling import WHITE_MAX_GAIN
from warptan.parallel import launch, launch_rows, rows_of
from warptan.sensing.likelihood import LIKELIHOODS, POSITION_PRIOR_PRECISION, Likelihood, without_offset
from warptan.sensing.sensors import AltimeterReading, PointCloud
from warptan.terrain.raycast import RayCaster, check_same_device


@dataclass
class ModelOutput:
    """Per-particle results of one measurement update, on the device. From :meth:`MeasurementModel.evaluate`: the
    caller's own arrays; from :meth:`MeasurementModel.launch` (the filter's path): the model's buffers, which the
    next ``stage``/``launch`` overwrites (on the CPU, ``.numpy()`` of them is a view, not a copy)."""

    loglik: wp.array
    """(N,) float32 log-likelihood (finite for every particle)."""
    error_m: wp.array
    """(N,) float32 paper error in m (NaN for a particle with no valid point)."""
    n_valid: wp.array
    """(N,) int32 number of points the particle could predict."""
    nis: wp.array
    """(N,) float32 normalised squared residual: mean over the received points of min((residual/σ)²,
    outlier_sigmas²), an unpredictable point counting ``outlier_sigmas²``."""
    residual_m: wp.array
    """(N, M) float32 residuals in m (NaN = invalid)."""
    meta: wp.array
    """(B, 2) float32 per filter: [valid received points, log-likelihood floor for a non-finite value]."""
    lam: wp.array | None = None
    """(N,) mat33 attitude information of each particle's residuals, ``Λ = Σ_j H_jᵀ H_j / σ_j²`` (rad⁻²), H_j the
    prediction's Jacobian w.r.t. the particle's attitude error dθ (zero for the altimeter)."""
    info: wp.array | None = None
    """(N,) vec3 ``b = Σ_j H_jᵀ r_j / σ_j²`` (rad⁻¹): with Λ, the linearised measurement of dθ in information form
    (the Kalman update of :mod:`warptan.kernels.mpf`)."""
    normal: wp.array | None = None
    """(N, M) vec3 scaled surface normal ``∇F / (∇F · u)`` at each ray's hit, 1/1 (ray casts): the predicted range's
    derivatives w.r.t. dθ and the position follow from it (:func:`warptan.kernels.likelihood.ray_jacobians`)."""
    vertical_m: wp.array | None = None
    """(N, M) float32 each received point's height above the map's surface, placed with the particle's pose (m, NaN
    where invalid; ray casts): what a gross miss scores (:func:`warptan.kernels.likelihood.acc_gated`)."""
    info_pos: wp.array | None = None
    """(N,) vec3 horizontal position information of each particle's residuals, ``Σ_j g_j g_jᵀ / σ_j²`` as (nn, ee, ne)
    (m⁻²), g_j the prediction's gradient w.r.t. the horizontal position; written by the models that cannot fix the
    position with one measurement (the altimeter; None for the models that can, ``fixes_per_scan``): the filter keeps
    its regularisation jitter within what one measurement resolves (:mod:`warptan.filter.mpf`)."""
    mode_post: wp.array | None = None
    """(N,) modes_vec the particles' map-error mode amplitudes after this scan, predicted to the next (whitened, in
    the modes of the table in use; zero without a stated map error): the filter keeps them as the next prior."""
    n_received: np.ndarray = field(default_factory=lambda: np.zeros(1, dtype=np.int64))
    """(B,) valid received points per filter (host; known without a sync)."""

    @property
    def all_points_invalid(self) -> bool:
        """Warning flag: no received point was valid (in any filter), every particle got the same score."""
        return bool(np.all(self.n_received == 0))


QUAT_NORM_TOL = 1e-3
"""How far from 1 the norm of a quaternion given to :meth:`MeasurementModel.evaluate` may be."""


def _check_pose_values(pos_n: wp.array, quat_nb: wp.array) -> None:
    """FilterError naming the first particle with a non-finite position or a quaternion that is not unit."""
    pos, quat = pos_n.numpy(), quat_nb.numpy()
    bad_pos = ~np.isfinite(pos).all(axis=1)
    if bad_pos.any():
        i = int(np.argmax(bad_pos))
        raise FilterError(f"pos_n[{i}] = {pos[i].tolist()} is not finite ({int(bad_pos.sum())} such particle(s))")
    with np.errstate(invalid="ignore"):
        bad = ~(np.abs(np.linalg.norm(quat.astype(np.float64), axis=1) - 1.0) <= QUAT_NORM_TOL)
    if bad.any():
        i = int(np.argmax(bad))
        raise FilterError(f"quat_nb[{i}] = {quat[i].tolist()} is not a unit quaternion [w, x, y, z] "
                          f"({int(bad.sum())} such particle(s); |q| must be 1 within {QUAT_NORM_TOL:g})")


def _as_batch(measurement, kind, model_name: str) -> list:
    items = list(measurement) if isinstance(measurement, (list, tuple)) else [measurement]
    if not items:
        raise FilterError(f"{model_name} model got an empty list of measurements")
    for item in items:
        if not isinstance(item, kind):
            raise FilterError(f"{model_name} model needs a {kind.__name__}, got {type(item).__name__}")
    return items


class MeasurementModel:
    """Base class: buffers, validation, staging; subclasses launch their kernels."""

    name = "base"
    err_kind = klik.ERR_MEAN_ABS
    recordable = True
    """Launches only through :mod:`warptan.parallel` (its launches can be recorded and replayed on the CPU)."""
    reading_type: type = PointCloud
    fixes_per_scan = False
    """One scan fixes the horizontal position by itself (a footprint of points): under a stated map error the
    filter lets that fix wander along the track (:meth:`Likelihood.fix_process`)."""

    def __init__(self, terrain, likelihood: Likelihood | None = None):
        self.terrain = terrain
        self._out: ModelOutput | None = None
        self._key = None
        self._host: dict[str, np.ndarray] = {}
        self._poses_ok: tuple = ()  # (pos_n, quat_nb, device): the pose arrays _check_poses last accepted
        self._uploads = Uploads()  # the scan's host-to-device copies (pinned on CUDA: they do not hold the host)
        self._table_uploads = Uploads()  # the mode table's, queued at once (never held in a graph: a table changes
        # at some scans only; a pageable assign on CUDA would wait for all the device work queued so far)
        self._att_cov: wp.array | None = None
        self._zero_att: wp.array | None = None
        self._modes: wp.array | None = None
        self._modes_host: np.ndarray | None = None
        self._modes_skip = 0
        self._scans = 0  # scans staged (the turn's clock)
        self._heading: tuple | None = None  # (the flight's horizontal direction, scans) at the last look
        self._turn = self._turn_built = 0.0  # the flight's heading change per scan at the last look, at the build
        self._pending: tuple | None = None  # a mode table built behind the updates (MODES_BEHIND)
        self._nominal: tuple | None = None  # the table's own modes, ρ, κᵃ and sensitivities (_place_modes)
        self._placed_xy: np.ndarray | None = None  # the ground points the modes in use were placed at
        self._built_quat: np.ndarray | None = None  # the platform's attitude the table in use was built under
        self._no_cloud: wp.array | None = None
        self._amp_scale = 1.0  # the stored amplitudes' factor for the next scan (a new per-point σ whitens them anew)
        self._truncation_var = 0.0  # what the per-point variance counts of the table's dropped modes (m²;
        # _count_truncation)
        self.modes_version = 0
        """Bumped whenever the mode table gets new modes (a rebuild; not a rescale: the modes stay)."""
        self._spectrum: tuple | None = None  # ((version, factors), mode_spectrum's array)
        self._mode_sums: wp.array | None = None  # the CPU's SIMD kernels' scratch rows (_simd_mode_sums)
        self.footprint_centre = np.zeros(2)
        """Mean horizontal offset (m, navigation frame) of the scan's nominal ground points from the aircraft (the
        last scan under a stated map error; :class:`~warptan.sensing.likelihood.RevisitMemory` reads it)."""
        self._mode_mean: wp.array | None = None
        self._mode_var: wp.array | None = None
        self._no_modes: tuple[wp.array, wp.array] | None = None
        self.modes_info: dict = {"n_modes": 0}
        """The map-error modes in use (:meth:`Likelihood.error_modes`'s summary; built at the first ``stage``)."""
        self.generation = 0
        """Bumped whenever an array or struct that launches hold is replaced (buffers reallocated, the likelihood or
        the bound attitude covariance reassigned): a recorded launch sequence or captured graph of an older
        generation is stale and must be re-recorded (see :class:`warptan.filter.mpf.MarginalizedParticleFilter`)."""
        self.likelihood = likelihood or Likelihood()

    @property
    def likelihood(self) -> Likelihood:
        """How residuals become a log-likelihood; may be reassigned between updates."""
        return self._likelihood

    @likelihood.setter
    def likelihood(self, value: Likelihood) -> None:
        if not isinstance(value, Likelihood):
            raise FilterError(f"likelihood must be a Likelihood, got {type(value).__name__}")
        self._likelihood = value
        self._modes = None  # rebuilt for the new likelihood at the next stage
        self.modes_info = {"n_modes": 0}
        self._truncation_var = 0.0  # (the new table's)
        self._params = self.params()
        self.generation += 1

    def mode_spectrum(self, factors: np.ndarray) -> np.ndarray | None:
        """``(len(factors), MAX_MODES)``: the current modes' one-scan variances per unit error variance were the error
        correlated over each of ``factors`` times the stated length (:meth:`~warptan.sensing.likelihood.Likelihood.
        mode_spectrum`; zero for the columns the table does not use), cached per table; None without one."""
        if self._modes_host is None or self._modes_geometry is None:
            return None
        key = (self.modes_version, tuple(float(f) for f in factors))
        if self._spectrum is None or self._spectrum[0] != key:
            xy, _along, sens = self._modes_geometry
            xy = xy if self._placed_xy is None else self._placed_xy
            m, n = len(xy), int(self.modes_info.get("n_modes", 0))
            lengths = self.likelihood.map_error_corr_m * np.asarray(factors, dtype=np.float64)
            spectrum = np.zeros((len(lengths), klik.MAX_MODES))
            spectrum[:, :n] = self.likelihood.mode_spectrum(xy, sens, self._modes_host[:m, :n], self.sigma_m, lengths,
                                                            self.absorbs_map_offset)
            self._spectrum = (key, spectrum)
        return self._spectrum[1]

    def restate_map_error(self, sigma_m: float, corr_m: float | None = None, white_m: float | None = None) -> None:
        """Use ``sigma_m`` as the stated map error's RMS from the next scan on, keeping the mode table's basis (its
        amplitudes are whitened by the point σ, which does not change: the filter's stored amplitudes stay valid;
        :class:`~warptan.sensing.learner.MapErrorLearner`). The modes and their correlations along the track do
        not depend on the RMS: the table in use is rescaled (:meth:`~warptan.sensing.likelihood.Likelihood.
        rescale_error_modes`), not rebuilt. A new correlation length ``corr_m`` changes the modes: the table is
        rebuilt at the next scan, the filter's amplitudes carried into the new modes by the basis change ``T``.

        The kernels' struct keeps the statement's RMS (``sigma_err``: the gross-miss gate's scale and the ray casts'
        geometry term, :meth:`params`) and the table's values change in place, so recorded launches and captured
        graphs stay valid: a restatement costs no re-capture on CUDA.

        ``white_m``: the map's own white error (``Likelihood.map_sigma_m``) learned anew. It changes the per-point σ,
        so the struct is rebuilt (a re-capture), the table's one-scan variances are those of the new whitening and
        the stored amplitudes, whitened by the old σ, are carried over by ``T = (σ_old / σ_new) I`` at the next
        scan."""
        if not self._likelihood.models_map_error:
            raise FilterError("restate_map_error needs a likelihood with a stated map error")
        old, old_point = self._likelihood.map_error_sigma_m, self.sigma_m
        if white_m is not None and float(white_m) != self._likelihood.map_sigma_m and self._likelihood.sigma_m is None:
            self._likelihood = dataclasses.replace(self._likelihood, map_sigma_m=float(white_m))
            self._whiten_anew(old_point)
        if corr_m is not None and float(corr_m) != self._likelihood.map_error_corr_m:
            self._likelihood = dataclasses.replace(self._likelihood, map_error_sigma_m=float(sigma_m),
                                                   map_error_corr_m=float(corr_m))
            self._count_truncation()  # (the old table's share until the new one's)
            self._modes_geometry, self._modes_skip = None, 0  # (rebuilt at the next stage, from the old table)
            return
        self._likelihood = dataclasses.replace(self._likelihood, map_error_sigma_m=float(sigma_m))
        self._count_truncation()  # (the dropped modes' variance scales with σ_e²)
        host = self._modes_host
        if host is not None and self._modes_geometry is not None:  # the same modes, their variances scaled
            m = host.shape[0] - klik.MODE_EXTRA_ROWS
            factor = (float(sigma_m) / old) ** 2 * (old_point / self.sigma_m) ** 2
            self._modes_host = host = self.likelihood.rescale_error_modes(host, m, factor)
            self._table_uploads.put("modes", self._modes, host)
            self.modes_info = {**self.modes_info, "k0": host[m + klik.MODE_K0].tolist()}
            if old_point != self.sigma_m:
                self.modes_version += 1  # (the spectrum is per unit of the point variance)

    def bind_attitude_cov(self, att_cov: wp.array | None) -> None:
        """Use ``att_cov`` ((B,) mat33 on the particles' device, rad²: each filter's Kalman covariance of dθ,
        kept current by its owner) to marginalise the per-point Gaussian over the attitude uncertainty; None
        (the default) is a zero covariance (the pose's attitude taken as exact)."""
        if att_cov is not self._att_cov:
            self._att_cov = att_cov
            self.generation += 1

    def _gates_misses(self) -> bool:
        """The likelihood is told its map is not the world, so gross misses score their point's height above the map
        (:func:`warptan.kernels.likelihood.map_not_world`: the ray casts then also write those heights)."""
        p = self._params
        return p.lik != klik.LIK_PAPER and (p.sigma_err > 0.0 or p.sigma_map > 0.0)

    def _bound_or_zero(self, bound: wp.array | None, zero_attr: str, device, b: int) -> wp.array:
        """A bound (B,) mat33 per-filter array when it fits ``device`` and ``b``, else the model's own zeros (kept in
        ``zero_attr``; reallocating it bumps :attr:`generation`)."""
        if bound is not None and bound.shape == (b,) and bound.device == device:
            return bound
        zero = getattr(self, zero_attr)
        if zero is None or zero.shape != (b,) or zero.device != device:
            zero = wp.zeros(b, dtype=wp.mat33, device=device)
            setattr(self, zero_attr, zero)
            self.generation += 1
        return zero

    def _attitude_cov(self, device, b: int) -> wp.array:
        return self._bound_or_zero(self._att_cov, "_zero_att", device, b)

    @property
    def sigma_m(self) -> float:
        """The per-point residual scale in m: :meth:`Likelihood.sigma_eff` and, under a stated map error, the variance
        that stands for the modes the table drops (:meth:`Likelihood.error_modes`' ``truncation_unit`` times
        ``σ_e²``; counted once it is :data:`TRUNCATION_MIN` of the point's variance)."""
        return math.sqrt(self._base_sigma_m() ** 2 + self._truncation_var)

    def _base_sigma_m(self) -> float:
        """The per-point σ without the dropped modes' variance (what a mode table is built for)."""
        return self.likelihood.sigma_eff(self.surface_mismatch_m())

    @property
    def dropped_var_m2(self) -> float:
        """The energy (m², a point's mean) of the stated error in the modes the table in use drops (its
        ``dropped_unit`` times ``σ_e²``): what the residuals hold outside the modes besides white error."""
        lk = self._likelihood
        unit = float(self.modes_info.get("dropped_unit", 0.0))
        return lk.map_error_sigma_m**2 * unit if lk.models_map_error else 0.0

    TRUNCATION_MIN = 0.01
    """The dropped modes' variance is counted in the per-point σ once it is at least this fraction of the point's
    variance without it (over a map error correlated over kilometres it is 1e-5 of it and counts nothing)."""
    TRUNCATION_MOVE = 0.2
    """…and counted anew when it moved by more than this fraction (each change rebuilds the kernels' struct: a
    re-capture on CUDA)."""

    def _count_truncation(self) -> None:
        """The dropped modes' variance for the statement now (the table's ``truncation_unit`` times ``σ_e²``) into the
        per-point σ when it is due (:data:`TRUNCATION_MIN`, :data:`TRUNCATION_MOVE`; :meth:`_whiten_anew`)."""
        lk = self._likelihood
        unit = float(self.modes_info.get("truncation_unit", 0.0))
        target = lk.map_error_sigma_m**2 * unit if lk.models_map_error else 0.0
        if target < self.TRUNCATION_MIN * self._base_sigma_m() ** 2:
            target = 0.0
        now = self._truncation_var
        if target == now or (now > 0.0 and target > 0.0 and abs(target / now - 1.0) <= self.TRUNCATION_MOVE):
            return
        old_point = self.sigma_m
        self._truncation_var = target
        self._whiten_anew(old_point)

    def _whiten_anew(self, old_point: float) -> None:
        """After the per-point σ moved from ``old_point`` (a learned white error, the dropped modes' variance): the
        kernels' struct rebuilt for it (a re-capture; the statement's ``sigma_err`` and the modes kept), and the
        stored amplitudes, whitened by the old σ, carried by ``σ_old / σ_new`` at the next scan's look."""
        statement = self._params.sigma_err
        self._params = self.params()
        self._params.sigma_err, self._params.n_modes = statement, klik.MAX_MODES
        self.generation += 1
        self._amp_scale *= old_point / self.sigma_m
        self._modes_skip = 0

    def surface_mismatch_m(self) -> float:
        """RMS difference (m) between the surface this model reads and the triangulated map: 0 for models that
        read the triangles (ray casts, ``surface=True``), the bilinear-vs-triangles RMS otherwise."""
        return 0.0 if getattr(self, "surface", True) else self.terrain.bilinear_mismatch_sigma_m

    def params(self) -> klik.LikParams:
        """The likelihood as the kernels' struct."""
        lk = self.likelihood
        p = klik.LikParams()
        p.err_kind, p.lik = int(self.err_kind), int(LIKELIHOODS[lk.kind])
        p.r_err, p.sigma, p.nu, p.k_out = float(lk.r_err), self.sigma_m, float(lk.nu), float(lk.outlier_sigmas)
        p.att_scale = self.sigma_m**2 / (lk.sigma_att(self.surface_mismatch_m()) ** 2 + self._truncation_var)
        p.pos_precision = POSITION_PRIOR_PRECISION if lk.project_position else -1.0
        p.n_modes = 0  # set by _ensure_modes when the first scan is staged
        p.sigma_err = float(lk.map_error_sigma_m) if lk.models_map_error else 0.0  # (a restatement keeps it)
        if lk.sigma_m is None:
            p.sigma_range = float(lk.sensor_sigma_m)
            p.sigma_map = math.sqrt(max(self.sigma_m**2 - lk.sensor_sigma_m**2, 0.0))
        else:
            p.sigma_range, p.sigma_map = float(lk.sigma_m), math.sqrt(self._truncation_var)
        return p

    def _buffers(self, device, n: int, b: int, m: int) -> ModelOutput:
        key = (device, n, b, m)
        if key != self._key:
            self._key = key
            self._out = ModelOutput(
                loglik=wp.empty(n, dtype=wp.float32, device=device),
                error_m=wp.empty(n, dtype=wp.float32, device=device),
                n_valid=wp.empty(n, dtype=wp.int32, device=device),
                nis=wp.empty(n, dtype=wp.float32, device=device),
                residual_m=wp.empty((n, m), dtype=wp.float32, device=device),
                meta=wp.empty((b, 2), dtype=wp.float32, device=device),
                lam=wp.zeros(n, dtype=wp.mat33, device=device),
                info=wp.zeros(n, dtype=wp.vec3, device=device),
                n_received=np.zeros(b, dtype=np.int64),
                normal=wp.empty((n, m), dtype=wp.vec3, device=device) if self.name == "raycast" else None,
                vertical_m=wp.empty((n, m), dtype=wp.float32, device=device) if self.name == "raycast" else None,
                mode_post=wp.zeros(n, dtype=klik.modes_vec, device=device),
                info_pos=None if self.fixes_per_scan else wp.zeros(n, dtype=wp.vec3, device=device),
            )
            self._staged = self._staging_buffer(device, b, m)
            self.generation += 1
        return self._out

    def evaluate(self, pos_n: wp.array, quat_nb: wp.array, measurement) -> ModelOutput:
        """Log-likelihood of the received measurement (or a list of B, one per filter of a batch) at the poses.

        The poses are checked first (finite positions; unit quaternions, ``|‖q‖ − 1| ≤ 1e-3``: a zero or NaN
        quaternion is an error, not the identity or the log-likelihood floor). The returned arrays are the
        caller's: copies that a later call does not overwrite (this allocates them; the filter's step uses
        :meth:`stage` and :meth:`launch`, which reuse the model's buffers and allocate nothing per step)."""
        self.stage(measurement, pos_n, quat_nb)
        _check_pose_values(pos_n, quat_nb)
        out = self.launch(pos_n, quat_nb)
        return dataclasses.replace(out, **{f.name: wp.clone(getattr(out, f.name))
                                           for f in dataclasses.fields(out)
                                           if isinstance(getattr(out, f.name), wp.array)},
                                   n_received=out.n_received.copy())

    def hold_device_work(self, buffers: dict) -> None:
        """Until :meth:`release_device_work`: :meth:`stage` writes the measurement into pinned buffers kept in the
        caller's ``buffers`` and holds its copies and launches instead of queuing them (see
        :meth:`warptan.device.Uploads.hold`; CUDA)."""
        self._uploads.hold(buffers)

    def release_device_work(self) -> list:
        """The device work :meth:`stage` held (callables, in order; the caller queues them before :meth:`launch`, in
        its graph)."""
        return self._uploads.release()

    def check(self, measurement) -> None:
        """Raise a FilterError for a measurement (or a batch's list) that :meth:`stage` would refuse, touching
        nothing: the filter checks a measurement before its interval moves anything, then stages it while the device
        integrates the interval."""
        self._m_of(_as_batch(measurement, self.reading_type, self.name))

    def stage(self, measurement, pos_n: wp.array, quat_nb: wp.array, attitude=None) -> ModelOutput:
        """Copy the measurement(s) into this model's device buffers for particles of shape ``pos_n``. ``attitude``:
        the platform's attitude quaternion (4,) for the map-error modes' geometry (a stated map error only; default
        the first particle's ``quat_nb``, which must then hold the poses already)."""
        items = _as_batch(measurement, self.reading_type, self.name)
        m = self._m_of(items)
        device = self._check_poses(pos_n, quat_nb)
        n, b = pos_n.shape[0], len(items)
        if n % b:
            raise FilterError(f"{n} particles cannot be split evenly over {b} filters")
        out = self._buffers(device, n, b, m)
        out.n_received[:] = self._fill(items, out.meta)
        self.n_per = n // b
        self.n_filters = b
        self._ensure_modes(device, quat_nb, attitude)
        if self._built_quat is not None:
            self._place_modes(self._built_quat)
        return out

    def _meta(self, n_received: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """(B, 2) float32 rows of ``meta`` (``klik.META_*``), written into ``out`` when given: each filter's received
        points and its log-likelihood floor (what a non-finite log-likelihood scores)."""
        k = self.likelihood.outlier_sigmas
        meta = np.empty((len(n_received), 2), dtype=np.float32) if out is None else out
        if len(n_received) == 1:  # one filter: Python numbers, the same float64 product (NumPy on 2 values: ~3 µs)
            n = int(n_received[0])
            meta[0, klik.META_RECEIVED] = n
            meta[0, klik.META_FLOOR] = -0.5 * k * k * max(1, n)
            return meta
        meta[:, klik.META_RECEIVED] = n_received
        meta[:, klik.META_FLOOR] = -0.5 * k * k * np.maximum(1, n_received)
        return meta

    MODES_CHECK_EVERY = 10
    """Scans between two looks at the map-error modes' geometry while it holds (1 s of flight at 10 Hz turns a 3°/s
    turn by 3°, far inside :data:`MODES_REBUILD`). A look's host work (the scan's nominal footprint and the rebuild
    test) took a median 0.18 ms on an H200 host against 0.02 ms for a stage without it; at every 5 scans the looks
    were about a fifth of the learned path's host cost there (``scripts/profile_update_host.py``). Looking every 10
    scans instead of 5 (with the revisit memory and the learner's readings halved too) left S8 and S2 learned over
    the ``biased`` and ``short`` families within their seeds' noise (20 seeds × 4 worlds, CHANGELOG session 16)."""
    MODES_REBUILD = 0.25
    """The map-error mode table is rebuilt when a scan's nominal ground geometry moved by more than this fraction
    of the footprint's size since it was built (a turn, a climb). Measured on this code (3σ coverage N/E/D,
    ``run_scenario_batch(ID, [0, 1, 2, 3], world_error_rms_m=5, world_error_corr_m=1000, world_seed=1000,
    duration_s=90, map_error_rms_m=5, map_error_corr_m=1000)`` with this attribute set, CPU): never rebuilt, S1
    99/88/97 %; at 25 %, S1 98/100/85 %, S8 92/91/100 %; at 5 %, S1 99/98/100 %, S8 96/92/100 % — four seeds do
    not separate 5 % from 25 %, and ``results/world`` ran at 25 %. (With the points' own ranges as the footprint,
    an earlier version, rebuilding at every 5 % had cost S8's down axis: 43 %.)"""

    @property
    def modes_look_due(self) -> bool:
        """True when the next :meth:`stage` looks at the scan's geometry (a stated map error; every
        :data:`MODES_CHECK_EVERY` scans, and at once after a new table or statement): the one stage that reads
        the platform's attitude (its ``attitude``, else the first particle's)."""
        return self.likelihood.models_map_error and (self._modes is None or self._modes_geometry is None
                                                     or (self._pending is None and self._modes_skip <= 0))

    def _ensure_modes(self, device, quat_nb: wp.array, attitude=None) -> None:
        """The map-error mode table on ``device``: a zero table without a stated map error; with one, the modes of
        the current scan's ground geometry (the first filter's scan placed with its first particle's attitude),
        rebuilt when that geometry moved (:data:`MODES_REBUILD`); the attitude is ``attitude`` when given, else
        the first particle's. The table keeps its array (a captured graph
        reads the new values) and ``n_modes`` stays :data:`~warptan.kernels.likelihood.MAX_MODES` (unused
        columns are zero)."""
        self._scans += 1
        m = self._staged.shape[1] if self._staged.ndim == 2 else 1
        rows = m + klik.MODE_EXTRA_ROWS
        fresh = self._modes is None or self._modes.device is not device or self._modes.shape[0] != rows
        if fresh:
            self._modes = wp.zeros(rows, dtype=klik.modes_vec, device=device)
            self._modes_host = None
            self._modes_geometry = None
            self._pending = None
            self._nominal = self._placed_xy = self._built_quat = None
            self._params.n_modes = klik.MAX_MODES if self.likelihood.models_map_error else 0
            self.generation += 1
        if not self.likelihood.models_map_error:
            return
        if not fresh and self._pending is not None and self._modes_due():
            return
        if not fresh and self._modes_skip > 0:  # the geometry looked at again every MODES_CHECK_EVERY scans
            self._modes_skip -= 1
            return
        quat = np.asarray(attitude if attitude is not None else quat_nb[:1].numpy()[0], dtype=np.float64).reshape(4)
        xy, sens, along = self._scan_geometry(quat)
        self.footprint_centre = xy.mean(axis=0)  # where the scan reads the map, from the aircraft (m)
        self._read_turn(along)
        old, host = self._modes_geometry, self._modes_host
        size = max(float(np.ptp(xy, axis=0).max()) if len(xy) > 1 else 0.0, 1.0)
        span = self.likelihood.map_error_corr_m / max(self.likelihood.track_step_m, 1e-9)  # steps in one length
        turned = abs(np.clip(self._turn * span, -1.0, 1.0) - np.clip(self._turn_built * span, -1.0, 1.0))
        if old is not None and old[0].shape == xy.shape and np.abs(old[0] - xy).max() <= self.MODES_REBUILD * size \
                and np.abs(old[1] - along).max() <= self.MODES_REBUILD and turned <= self.MODES_REBUILD_TURN:
            if self._amp_scale != 1.0:  # the amplitudes whitened anew (restate_map_error's white_m)
                host[m + klik.MODE_T:] = self._amp_scale * np.eye(klik.MAX_MODES, dtype=np.float32)
                self._table_uploads.put("modes", self._modes, host)
                self._amp_scale = 1.0
            elif not np.array_equal(host[m + klik.MODE_T:], np.eye(klik.MAX_MODES)):  # the basis change applied once
                host[m + klik.MODE_T:] = np.eye(klik.MAX_MODES, dtype=np.float32)
                self._table_uploads.put("modes", self._modes, host)
            else:
                self._modes_skip = self.MODES_CHECK_EVERY - 1
            return
        self._turn_built = self._turn
        if host is not None and self.MODES_BEHIND > 0:  # built on the worker, applied MODES_BEHIND scans on
            self._pending = (_modes_worker().submit(self.likelihood.error_modes, xy, sens, self._base_sigma_m(), along,
                                                    self.absorbs_map_offset, self._turn),
                             self.MODES_BEHIND, self.likelihood, self._base_sigma_m(), (xy, along, sens), quat)
            return
        self._apply_modes(self.likelihood.error_modes(xy, sens, self._base_sigma_m(), along, self.absorbs_map_offset,
                                                      self._turn), (xy, along, sens), quat)

    MODES_REBUILD_TURN = 0.3
    """The table is rebuilt too when the flight's turn over one correlation length (its heading change per scan ×
    ``L / s``, capped at 1 rad) changed by more than this (rad) since it was built: the attitude's sharing of the
    modes depends on it (:meth:`~warptan.sensing.likelihood.Likelihood.error_modes`' ``turn``)."""

    def _read_turn(self, along: np.ndarray) -> None:
        """The flight's heading change per scan (rad, positive: the heading grows) from the flight's horizontal
        direction ``along`` now and at the last look, over the scans staged in between."""
        if self._heading is not None and self._scans > self._heading[1]:
            was = self._heading[0]
            change = math.atan2(was[0] * along[1] - was[1] * along[0], float(was @ along))
            self._turn = change / (self._scans - self._heading[1])
        self._heading = (np.asarray(along, dtype=np.float64).copy(), self._scans)

    MODES_BEHIND = 8
    """Scans between the one whose geometry asks for a new mode table and the one that first uses it: the table
    (eigenvectors of the scan's error covariance, its sharing along the track: 3-5 ms of NumPy on one BLAS thread,
    :func:`warptan.device.one_blas_thread`) is built on a worker
    thread behind the filter's updates, which keep the table in use until then. Eight scans are 0.8 s at 10 Hz (a
    3°/s turn turns 2.4° more; the table is rebuilt when the footprint moved by :data:`MODES_REBUILD` of its size)
    and 5 ms of a GPU's updates (at two scans the GPU's host waited for the worker). The scan that uses it is fixed,
    whatever the threads' timing: a run's results do not depend on it. 0: built at once. A statement restated while
    it is built (a new RMS, length or per-point σ) has it built again at once for the restatement."""

    def _modes_due(self) -> bool:
        """A table built behind the updates (:data:`MODES_BEHIND`) applied at its scan (the next scan looks at the
        geometry again, and sets the basis change back to the identity); True: this scan's table is settled."""
        job, left, likelihood, sigma, geometry, quat = self._pending
        if left > 1:
            self._pending = (job, left - 1, likelihood, sigma, geometry, quat)
            return True
        built = job.result()  # (long done on a CPU's updates; on a GPU's, 8 scans are about the table's time)
        self._pending = None
        if likelihood is not self.likelihood or sigma != self._base_sigma_m():  # restated meanwhile: for it now
            xy, along, sens = geometry
            built = self.likelihood.error_modes(xy, sens, self._base_sigma_m(), along, self.absorbs_map_offset,
                                                self._turn)
        self._apply_modes(built, geometry, quat)
        return True

    def _apply_modes(self, built: tuple, geometry: tuple, quat: np.ndarray | None = None) -> None:
        """Use the mode table ``built`` (:meth:`Likelihood.error_modes`' table and summary) of the scan geometry
        ``geometry`` (xy, along, sensitivities) looked at under the attitude ``quat``."""
        table, info = built
        host = self._modes_host
        m = table.shape[0] - klik.MODE_EXTRA_ROWS
        self.modes_info = {**info, "rebuilds": self.modes_info.get("rebuilds", 0) + 1}
        self._count_truncation()
        if self._truncation_var > 0.0:  # built for the σ without the dropped modes: its variances for the σ with them
            table = self.likelihood.rescale_error_modes(table, m, (self._base_sigma_m() / self.sigma_m) ** 2)
            self.modes_info["k0"] = table[m + klik.MODE_K0].tolist()
        # T = U_newᵀ U_old carries the stored amplitudes into the new modes; a first table (or one for a new
        # likelihood) carries nothing: T = 0 gives the one-scan prior whatever a filter stored
        table[m + klik.MODE_T:] = 0.0 if host is None else self._amp_scale * (table[:m].T @ host[:m])
        self._amp_scale = 1.0
        self._table_uploads.put("modes", self._modes, table)
        self._modes_host = table
        self._modes_geometry = geometry
        sens = geometry[2]
        n = int(info.get("n_modes", 0))
        self._nominal = (table[:m, :n].astype(np.float64), table[m + klik.MODE_RHO, :n].astype(np.float64),
                         np.asarray(info.get("sharing_att", np.ones(n)), dtype=np.float64)[:n], np.asarray(sens))
        self._placed_xy = None
        self._built_quat = quat
        self.modes_version += 1
        self._read_modes_near(table, m, sens)

    def _read_modes_near(self, table: np.ndarray, m: int, sens: np.ndarray) -> None:
        """:attr:`mode_reads` of the table ``table`` in use (``m`` points, sensitivities ``sens``)."""
        near = np.abs(sens) <= WHITE_MAX_GAIN
        self.mode_reads = ((table[:m][near] ** 2).sum(axis=0) >= 0.5).astype(np.float32)

    mode_reads: np.ndarray = np.ones(klik.MAX_MODES, dtype=np.float32)
    """Per mode of the table in use, 1 where at least half its weight lies on points whose sensitivity to the map is
    at most :data:`~warptan.kernels.filter.resampling.WHITE_MAX_GAIN` (within 48° of the vertical, where the
    table's flat-ground sensitivity holds), else 0: the modes the map-error learner reads the RMS from. A banked
    scan's grazing rays (1/u_z up to 10) claim more error than they see when they meet a hill face on; read from
    them, the learned RMS sank (S5, 60° bank: the told 5 m to 1 m, 3σ coverage 80 %; told and not learning, 98 %)."""

    @property
    def staged_cloud(self) -> wp.array:
        """The staged scans' rows ((B, M) :data:`~warptan.kernels.likelihood.cloud_row`: point, direction, range,
        valid), or one zero row for a model whose staged measurement is not a point cloud (the altimeter)."""
        if self._staged.ndim == 2 and self._staged.dtype == klik.cloud_row:
            return self._staged
        if self._no_cloud is None or self._no_cloud.device != self._out.loglik.device:
            self._no_cloud = wp.zeros((1, 1), dtype=klik.cloud_row, device=self._out.loglik.device)
        return self._no_cloud

    @property
    def mode_table(self) -> wp.array | None:
        """The map-error mode table the launches read (None before the first ``stage``; see :meth:`_ensure_modes`):
        the filter's end of an update reads its ρ, k⁰ and basis change rows."""
        return self._modes

    def bind_mode_state(self, mean: wp.array | None, var: wp.array | None) -> None:
        """Use ``mean`` ((N,) modes_vec: each particle's map-error mode amplitudes, whitened, predicted to this scan)
        and ``var`` ((B,) modes_vec: each filter's variances of them; negative: none yet) as the modes' prior,
        kept by their owner (the filter, which stores the launches' ``mode_post`` after an update); None (the
        default) is the one-scan prior (zero mean, variance ``k⁰``) for every scan."""
        if mean is not self._mode_mean or var is not self._mode_var:
            self._mode_mean, self._mode_var = mean, var
            self.generation += 1

    def _mode_state(self, device, n: int, b: int) -> tuple[wp.array, wp.array]:
        mean, var = self._mode_mean, self._mode_var
        if mean is not None and var is not None and mean.shape == (n,) and var.shape == (b,) and mean.device == device:
            return mean, var
        d = self._no_modes
        if d is None or d[0].shape != (n,) or d[1].shape != (b,) or d[0].device != device:
            d = self._no_modes = (wp.zeros(n, dtype=klik.modes_vec, device=device),
                                  wp.full(b, klik.modes_vec(-1.0), dtype=klik.modes_vec, device=device))
            self.generation += 1
        return d

    @property
    def absorbs_map_offset(self) -> bool:
        """The prediction moves with the particle's altitude, so a map-error offset over the scan is a vertical
        shift the particles carry (:meth:`Likelihood.error_modes`' ``absorb_offset``): ray casts and the sliding
        grid; the altimeter only without a barometer."""
        return True

    def _scan_geometry(self, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The current scan's horizontal ground offsets (M, 2, navigation frame), each residual's sensitivity to a
        vertical map error (M,) and the horizontal unit vector of the flight (2,)."""
        return np.zeros((1, 2)), np.ones(1), _forward(quat)

    def _ground_points(self, quat: np.ndarray) -> np.ndarray | None:
        """The scan's ground points as measured (M, 2), for :meth:`_place_modes`; None: a model without a footprint
        (its modes stay where the table put them)."""
        return None

    PLACE_MODES = False
    """Move the map-error modes to each scan's ground points as measured (:meth:`_place_modes`). Off by default: with
    it the fused and the separate forms of an update (``tests/test_mpf.py::test_block_forms_equal_the_separate_kernels``
    and the batch against separate runs) no longer give the same bits, even with the basis change kept the identity
    and the table's attitude fixed at its build; the cause is not found yet (CHANGELOG)."""

    @property
    def places_modes(self) -> bool:
        """The map-error modes follow each scan's ground points as measured (:meth:`_place_modes`, when
        :data:`PLACE_MODES`): a stated map error and a model whose scan has a footprint."""
        return self.PLACE_MODES and self.likelihood.models_map_error and self.fixes_per_scan

    PLACE_ITERATIONS = 2
    """Subspace iterations of :meth:`_place_modes` from the table's own modes (each scan starts from them, so a scan's
    modes do not depend on the scans before)."""

    def _place_modes(self, quat: np.ndarray) -> None:
        """The table's modes moved to this scan's ground points as measured (a point-cloud model under a stated map
        error; ``quat`` the platform's attitude the table was built under: the points' distances, all the modes depend
        on, do not change with the heading, and the copy of the platform's pose read at every scan differed in its
        last bits between the filter's update forms, which every scan's modes then followed; a roll or pitch that
        moved the footprint by :data:`MODES_REBUILD` of its size rebuilds the table).

        The table (:meth:`_ensure_modes`) is built over the nominal footprint, every ray meeting the scan's median
        ground level, which keeps its sharing along the track a smooth function of the flight. The points lie
        where their ranges put them: over a footprint of hills tens of metres off (S8's ±100 m of relief at 30° off
        the nadir), where a 5 m / 1 km error's gradient of about 7 mrad leaves ~0.4 m a point outside the nominal
        modes, shaped like the terrain's heights, against a σ of 0.5 m over a map on the world's posts: the Kalman
        part read it as the roll, the same in every scan over one error's tilt. So at every scan the modes are
        those of ``C = P A R(x) A P`` at the measured points ``x`` (the same sensitivities ``A``, offset projection
        ``P`` and correlation ``R`` as the table's): :data:`PLACE_ITERATIONS` subspace iterations from the table's
        modes (``Q ← orth(C Q)``) and the Rayleigh–Ritz step (``Qᵀ C Q = V Λ Vᵀ``, ``U ← Q V``; a few hundred µs of
        NumPy for 100 points, against 3–5 ms for the table's full build). The one-scan variances are
        ``k⁰_i = σ_e² λ_i / σ²``; the along-track correlations ``ρ_i`` and the attitude's sharing ``κᵃ_i`` are the
        table's, carried to the moved modes by their overlaps ``W = U_tableᵀ U`` (``ρ_i = Σ_k W_ki² ρ_k``); the basis
        change ``T = Uᵀ U_before`` carries the filters' amplitudes.

        The attitude's weights ``cᵃ_i = κ k⁰_i / (1 + κ k⁰_i)`` take ``κ`` at least the sharing of one ground point
        (:meth:`~warptan.sensing.likelihood.Likelihood.point_sharing`, ≈ √π L / s): a scan reads the attitude
        through mode i with a coefficient that follows the terrain under it, so what the field's own correlation
        cancels along a straight line (``∫ ρ_i = 0`` for an along-track slope: κ_i = 1) does not cancel in the
        reading; ``Σ_kl c_k c_l ρ_i(k − l) ≤ Σ_k c_k² Σ_l |ρ_i(l)|``, and ``Σ_l |ρ_i|`` of a Gaussian field's
        pattern is at most about a point's. Checked in NumPy on S8's 1200 scans at the true pose (the posts world
        of seed 2003; 100 Gaussian error fields, the readings' true spread against the claimed, roll/pitch/yaw):
        nominal modes 5.0/3.2/3.3×, placed 6.6/2.9/1.9×, placed with the floor 1.07/0.87/0.98×, placed and every
        mode kept out of the attitude 1.01/1.00/1.01× (its σ 15 % wider). Measured in the filter (S8 told over a
        ``posts`` world of 5 m / 1 km, world seed 2000, 8 seeds, CPU; converged horizontal RMSE, north/east 3σ
        coverage, roll's 3σ coverage): nominal modes 2.47 m, 99/55 %, roll 0 %; placed (per-scan eigenvectors)
        1.86 m, 97/94 %, 90 %; placed with the floor 1.76 m, 100/98 %, 100 %."""
        host, nominal = self._modes_host, self._nominal
        if host is None or nominal is None or not self.places_modes:
            return
        xy = self._ground_points(quat)
        u_table, rho_table, kappa_table, sens = nominal
        m, n = u_table.shape
        if xy is None or xy.shape[0] != m or n == 0:
            return
        lk = self._likelihood
        length = lk.map_error_corr_m
        d2 = np.sum((xy[:, None, :] - xy[None, :, :]) ** 2, axis=2)
        o = sens / max(float(np.linalg.norm(sens)), 1e-300) if self.absorbs_map_offset else None
        cov = without_offset((sens[:, None] * sens[None, :]) * np.exp(-d2 / (length * length)), o)
        before = host[:m, :n].astype(np.float64)
        with one_blas_thread():
            q = u_table
            for _ in range(self.PLACE_ITERATIONS):
                q, _r = np.linalg.qr(cov @ q)
            lam, vec = np.linalg.eigh(q.T @ cov @ q)
        order = np.argsort(lam)[::-1]
        lam, modes = np.maximum(lam[order], 0.0), q @ vec[:, order]
        overlap = (u_table.T @ modes) ** 2  # W_ki²
        rho = rho_table @ overlap
        kappa = np.maximum(kappa_table @ overlap, lk.point_sharing())
        k_one = lk.map_error_sigma_m**2 * lam / self.sigma_m**2
        table = host.copy()
        table[:m, :n] = modes.astype(np.float32)
        table[m + klik.MODE_K0, :n] = k_one.astype(np.float32)
        table[m + klik.MODE_C0, :n] = (k_one / (1.0 + k_one)).astype(np.float32)
        table[m + klik.MODE_RHO, :n] = rho.astype(np.float32)
        table[m + klik.MODE_CA, :n] = (kappa * k_one / (1.0 + kappa * k_one)).astype(np.float32)
        t = np.zeros((klik.MAX_MODES, klik.MAX_MODES))
        t[:n, :n] = modes.T @ before
        # (a basis change the table's own step left for this scan, a new table's or a new whitening's, comes first)
        upload = table.copy()
        upload[m + klik.MODE_T:] = (t @ host[m + klik.MODE_T:].astype(np.float64)).astype(np.float32)
        self._table_uploads.put("modes", self._modes, upload)
        table[m + klik.MODE_T:] = np.eye(klik.MAX_MODES, dtype=np.float32)  # (applied: the next scan's starts at I)
        self._modes_host = table
        self._placed_xy = xy
        self.modes_version += 1
        self._read_modes_near(table, m, sens)

    def launch(self, pos_n: wp.array, quat_nb: wp.array) -> ModelOutput:
        """Launch the model on the staged measurement (device work only: can be captured in a graph)."""
        if self._out is None:
            raise RuntimeError(f"{self.name} model: stage() a measurement before launch()")
        self._launch(pos_n, quat_nb, self._out, self._out.loglik.device)
        return self._out

    def _check_poses(self, pos_n: wp.array, quat_nb: wp.array):
        ok = self._poses_ok
        if ok and ok[0] is pos_n and ok[1] is quat_nb:  # (a filter stages with the same arrays every update)
            return ok[2]
        device = check_same_device(pos_n=pos_n, quat_nb=quat_nb)
        if pos_n.dtype != wp.vec3 or quat_nb.dtype != wp.vec4:
            raise FilterError(f"poses must be vec3 positions and vec4 quaternions, got {pos_n.dtype}, {quat_nb.dtype}")
        if pos_n.shape != quat_nb.shape:
            raise FilterError(f"pos_n has shape {pos_n.shape} but quat_nb {quat_nb.shape}")
        self._poses_ok = (pos_n, quat_nb, device)
        return device


class _PointCloudModel(MeasurementModel):
    fixes_per_scan = True

    @staticmethod
    def _m_of(items) -> int:
        m = len(items[0].ranges_m)
        if any(len(c.ranges_m) != m for c in items):
            raise FilterError(f"the point clouds of a batch must have the same number of points, got "
                             f"{sorted({len(c.ranges_m) for c in items})}")
        return m

    @staticmethod
    def _staging_buffer(device, b, m):
        return wp.empty((b, m), dtype=klik.cloud_row, device=device)

    def _simd_mode_sums(self, device, n: int):
        """``rows(a, b)``: the extra argument of the CPU's SIMD kernels (:mod:`warptan.kernels.simd`) for the
        particles ``a:b``, their scratch rows of the map-error modes' sums (one element, unused, without modes);
        none for the CUDA kernels."""
        if not device.is_cpu:
            return lambda a, b: []
        need = n if self._params.n_modes > 0 else 1
        sums = self._mode_sums
        if sums is None or sums.shape[0] < need or sums.device is not device:
            sums = self._mode_sums = wp.empty(need, dtype=klik.modes_sums_vec, device=device)
        if self._params.n_modes == 0:
            return lambda a, b: [sums]
        return lambda a, b: [rows_of(sums, a, b)]

    def _rays(self, quat: np.ndarray) -> tuple:
        """The first filter's staged scan under the attitude ``quat``: ``(rot, u, rng, down, ok, agl)``, the rotation,
        the rays in the navigation frame (float64), their ranges, their down components (at least 0.1), the rays with
        a range and more than 6° below the horizon, and the scan's median ground level under the aircraft (m)."""
        from warptan.nav.frames import quat_to_mat

        dirs, rng, _ = self._host["first"]  # the first filter's cloud as staged (float32 values)
        rot = quat_to_mat(quat / max(float(np.linalg.norm(quat)), 1e-12))
        u = dirs @ rot.T
        down = np.maximum(u[:, 2], 0.1)
        ok = (u[:, 2] > 0.1) & np.isfinite(rng)
        agl = _median((rng * u[:, 2])[ok]) if ok.any() else 1.0
        return rot, u, rng, down, ok, agl

    def _scan_geometry(self, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        rot, u, _rng, down, _ok, agl = self._rays(quat)
        # the nominal footprint: every ray meets the scan's median ground level (a smooth function of the altitude
        # and attitude; the points' own ranges moved it with every hill, and the modes with it)
        xy = (u * (agl / down)[:, None])[:, :2]
        sens = 1.0 / down if self.name == "raycast" else np.ones(len(u))
        return xy, sens, _forward(quat, rot)

    def _ground_points(self, quat: np.ndarray) -> np.ndarray:
        """The scan's ground points as measured (M, 2: horizontal offsets from the aircraft, navigation frame, m): each
        ray's own range along its direction under the platform's attitude ``quat``; a ray without a range (or
        within 6° of the horizon) keeps its nominal place (:meth:`_scan_geometry`)."""
        _rot, u, rng, down, ok, agl = self._rays(quat)
        return (u * np.where(ok, rng, agl / down)[:, None])[:, :2]

    def _fill(self, items, meta: wp.array) -> np.ndarray:
        """The clouds into the staged rows and ``meta``; returns each cloud's finite ranges."""
        b, m = self._staged.shape
        device = self._staged.device
        # the batch at once: the ranges and the meta rows go up as one copy, a kernel writes the rows and the meta
        # (:func:`cloud_rows_kernel`); the directions of one pattern that every cloud shares (a sensor's scans) go
        # up once
        first = items[0].dirs_s
        same = len(items) == 1 or all(cloud.dirs_s is first for cloud in items)
        cols = m + klik.CLOUD_META_COLS
        ranges = self._host.get("ranges")
        if ranges is None or ranges.shape != (b, cols):
            ranges = self._host["ranges"] = np.empty((b, cols), dtype=np.float32)
        if b == 1:  # one filter: one row (the batch's 2-D reductions cost a step ~3 µs more)
            row = ranges[0, :m]
            row[:] = items[0].ranges_m
            n_received = np.array([np.count_nonzero(np.isfinite(row))])
        else:
            for k, cloud in enumerate(items):
                ranges[k, :m] = cloud.ranges_m
            n_received = np.isfinite(ranges[:, :m]).sum(axis=1).astype(np.int64)
        self._meta(n_received, ranges[:, m:])
        dev_ranges = self._host.get("dev_ranges")
        if dev_ranges is None or dev_ranges.shape != (b, cols) or dev_ranges.device is not device:
            dev_ranges = self._host["dev_ranges"] = wp.empty((b, cols), dtype=wp.float32, device=device)
        self._uploads.put("ranges", dev_ranges, ranges)
        if same:
            kept = self._host.get("dirs")
            if kept is None or kept[1].device is not device or kept[1].shape != (1, m):
                kept = self._host["dirs"] = (first, wp.array(first[None].astype(np.float32), dtype=wp.vec3,
                                                              device=device))
            elif kept[0] is not first:  # another pattern of as many rays (a log's clouds): into the same array
                self._uploads.put("dirs", kept[1], first[None].astype(np.float32))
                kept = self._host["dirs"] = (first, kept[1])
            dirs = kept[1]
        else:  # each cloud its own directions: into one (B, M) array kept for this shape
            dirs = self._host.get("dirs_each")
            if dirs is None or dirs.shape != (b, m) or dirs.device != device:
                dirs = self._host["dirs_each"] = wp.empty((b, m), dtype=wp.vec3, device=device)
            self._uploads.put("dirs_each", dirs, np.stack([cloud.dirs_s for cloud in items]).astype(np.float32))
        cmd = self._host.get("rows_cmd")  # recorded once for these arrays (a launch packs its arguments every time)
        if cmd is None or cmd[0] is not dirs or cmd[1] is not dev_ranges or cmd[2] is not self._staged \
                or cmd[3] is not meta:
            cmd = self._host["rows_cmd"] = (dirs, dev_ranges, self._staged, meta, wp.launch(
                klik.cloud_rows_kernel, dim=(b, m), inputs=[dev_ranges, dirs], outputs=[self._staged, meta],
                device=device, record_cmd=True))
            self.generation += 1  # (a graph that holds the launch, :meth:`hold_device_work`, holds these arrays)
        if not self._uploads.later(cmd[4].launch):
            cmd[4].launch()
        if self.likelihood.models_map_error:  # the modes' scan geometry reads it (:meth:`_scan_geometry`)
            kept = self._host.get("first")
            dirs = kept[0] if kept is not None and kept[2] is first else first.astype(np.float32).astype(np.float64)
            self._host["first"] = (dirs, ranges[0, :m].astype(np.float64), first)  # (directions once per pattern)
        return n_received


def _median(values: np.ndarray) -> float:
    """``np.median`` of a non-empty 1-D array (the same value: the middle one, or the mean of the two), without its
    generic machinery (a tenth of a millisecond per call)."""
    k = len(values) // 2
    if len(values) % 2:
        return float(np.partition(values, k)[k])
    part = np.partition(values, (k - 1, k))
    return float((part[k - 1] + part[k]) / 2.0)


_WORKER: ThreadPoolExecutor | None = None


def _modes_worker() -> ThreadPoolExecutor:
    """The thread that builds mode tables behind the filter's updates (:data:`MeasurementModel.MODES_BEHIND`)."""
    global _WORKER
    if _WORKER is None:
        _WORKER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="warptan-modes")
    return _WORKER


def _forward(quat: np.ndarray, rot: np.ndarray | None = None) -> np.ndarray:
    """The horizontal unit vector of the body's x axis (the flight direction in coordinated flight); ``rot``: the
    quaternion's rotation matrix when the caller has it."""
    from warptan.nav.frames import quat_to_mat

    if rot is None:
        rot = quat_to_mat(quat / max(float(np.linalg.norm(quat)), 1e-12))
    x = rot[:2, 0]
    norm = float(np.linalg.norm(x))
    return x / norm if norm > 1e-6 else np.array([1.0, 0.0])


def _block_dim(device) -> int | None:
    """Threads per particle of the likelihood kernels: a block on CUDA, one thread on the CPU."""
    return klik.BLOCK_DIM if device.is_cuda else None


class RaycastModel(_PointCloudModel):
    """Predict each point by casting the pattern ray from the particle's pose (paper eq. 6, 15).

    Args:
        terrain: The map DEM.
        likelihood: See :class:`Likelihood`.
        caster: Backend ("dda", "mesh", "bisection") and its parameters.
    """

    name = "raycast"
    err_kind = klik.ERR_AXES

    def __init__(self, terrain, likelihood: Likelihood | None = None, caster: RayCaster | None = None):
        super().__init__(terrain, likelihood)
        self.caster = caster or RayCaster("dda")

    def _launch(self, pos_n, quat_nb, out, device):
        self._launch_residuals(pos_n, quat_nb, out, device)
        self._launch_reduce(quat_nb, out, device)

    def _launch_residuals(self, pos_n, quat_nb, out, device):
        """The rays' casts: each (particle, point)'s range residual, scaled normal and (when gated) vertical."""
        lead = self.caster.launch_args(self.terrain, device)
        res, nrm, vert, cloud, n_per = out.residual_m, out.normal, out.vertical_m, self._staged, self.n_per
        # CUDA: one thread per ray; the CPU: one per particle, its rotation and origin check made once, DDA rays cast
        # in SIMD lanes (the same ranges and slopes)
        if device.is_cuda:
            kernel, cols, cost = kray.raycast_residual_kernel, res.shape[1], 20
        else:
            kernel = (ksimd_ray.raycast_residual_rows_simd_kernel if self.caster.backend == "dda"
                      else kray.raycast_residual_rows_kernel)
            cols, cost = None, 20 * res.shape[1]
        launch_rows(kernel, res.shape[0],
                    lambda a, b: ([*lead, a or 0, n_per, rows_of(pos_n, a, b), rows_of(quat_nb, a, b), cloud],
                                  [rows_of(res, a, b), rows_of(nrm, a, b), int(self._gates_misses()),
                                   rows_of(vert, a, b)]),
                    device, cols=cols, row_cost=cost)

    def _launch_reduce(self, quat_nb, out, device):
        """Each particle's log-likelihood and information from its residuals (:meth:`_launch_residuals`)."""
        res, nrm, vert, cloud, n_per = out.residual_m, out.normal, out.vertical_m, self._staged, self.n_per
        att = self._attitude_cov(device, self.n_filters)
        mean, var = self._mode_state(device, res.shape[0], self.n_filters)
        kernel, block = klik.reduce_loglik_kernels[device.is_cuda, self._params.n_modes > 0], _block_dim(device)
        sums = self._simd_mode_sums(device, res.shape[0])
        if device.is_cpu:  # the points as SIMD lanes (same per-point values)
            kernel = ksimd.reduce_loglik_simd_kernels[self._params.n_modes > 0]
        launch_rows(kernel, res.shape[0],
                    lambda a, b: ([a or 0, n_per, rows_of(res, a, b), rows_of(quat_nb, a, b), rows_of(nrm, a, b),
                                   rows_of(vert, a, b), cloud, att, self._params, self._modes, rows_of(mean, a, b),
                                   var, *sums(a, b)],
                                  [rows_of(out.error_m, a, b), rows_of(out.loglik, a, b), rows_of(out.nis, a, b),
                                   rows_of(out.n_valid, a, b), rows_of(out.lam, a, b), rows_of(out.info, a, b),
                                   rows_of(out.mode_post, a, b)]),
                    device, row_cost=res.shape[1], block_dim=block)


class SlidingModel(_PointCloudModel):
    """The sliding grid: read the map under each received point placed with the particle's pose (eq. 14, 16).

    Each residual has its own σ: the sensor's range noise propagated to it, ``|g_z| sqrt(σ_range² (∇F · u)² +
    σ_map²)`` (:func:`warptan.kernels.sliding.sliding_var`; σ_range = the likelihood's ``sensor_sigma_m``, or its
    ``sigma_m`` when given, σ_map its map and surface-mismatch part). With the range σ itself the best particle's NIS
    was 0.08 in S6 (60° bank, low) and 0.5 in S4, and the position bounds 4× and 1.7× the error; now 0.90–0.97.

    Args:
        terrain: The map DEM.
        likelihood: See :class:`Likelihood`.
        surface: Sample the triangulated surface instead of the bilinear height (the surface ray casts see).
            The shipped scenarios use it (``sensor.surface = "triangles"``): with the bilinear height the
            bilinear-vs-triangles mismatch, terrain-fixed rather than noise, biased the attitude information
            (S11 over the int16-quantised flat DEM: a 0.3° yaw bias at 0 % 3σ coverage; with triangles 0.017° at
            100 %, and S1/S2/S8 position RMSE 1.7–3.6× lower; 20 seeds, ``results/paper/compare_bilinear.md``).
    """

    name = "sliding"
    err_kind = klik.ERR_MEAN_ABS

    def __init__(self, terrain, likelihood: Likelihood | None = None, surface: bool = False):
        self.surface = bool(surface)
        super().__init__(terrain, likelihood)

    def _launch(self, pos_n, quat_nb, out, device):
        grid, surface, cloud, n_per = self.terrain.grid(device), int(self.surface), self._staged, self.n_per
        att = self._attitude_cov(device, self.n_filters)
        mean, var = self._mode_state(device, pos_n.shape[0], self.n_filters)
        kernel, block = kslide.sliding_loglik_kernels[device.is_cuda, self._params.n_modes > 0], _block_dim(device)
        sums = self._simd_mode_sums(device, pos_n.shape[0])
        if device.is_cpu:  # the points as SIMD lanes (same per-point values)
            kernel = ksimd.sliding_loglik_simd_kernels[self._params.n_modes > 0]
        launch_rows(kernel, pos_n.shape[0],
                    lambda a, b: ([a or 0, n_per, grid, surface, rows_of(pos_n, a, b), rows_of(quat_nb, a, b), cloud,
                                   att, self._params, self._modes, rows_of(mean, a, b), var, *sums(a, b)],
                                  [rows_of(out.residual_m, a, b), rows_of(out.error_m, a, b), rows_of(out.loglik, a, b),
                                   rows_of(out.nis, a, b), rows_of(out.n_valid, a, b), rows_of(out.lam, a, b),
                                   rows_of(out.info, a, b), rows_of(out.mode_post, a, b)]),
                    device, row_cost=3 * cloud.shape[1], block_dim=block)


class AltimeterModel(MeasurementModel):
    """Radar altimeter with barometric altitude: ``a^_i = h_baro - h(p_i)`` (paper eq. 8, 17).

    It takes :class:`~warptan.sensing.sensors.AltimeterReading` measurements; particle attitudes are not used.
    With a barometer the altimeter residual does not depend on a particle's altitude, so the barometer is
    also used as what it is, a measurement of altitude: each particle's log-likelihood gets
    ``-0.5 (h_baro + p_i,z)² / baro_sigma_m²`` (without it the vertical error would be unobservable).

    Args:
        terrain: The map DEM.
        likelihood: See :class:`Likelihood`.
        surface: Sample the triangulated surface instead of the bilinear height.
        use_baro: False predicts with each particle's own altitude ``-p_i,z`` (no barometer).
        baro_sigma_m: Barometer noise σ for its altitude term, m.
    """

    name = "altimeter"
    err_kind = klik.ERR_SIGNED
    reading_type = AltimeterReading

    def __init__(self, terrain, likelihood: Likelihood | None = None, surface: bool = False, use_baro: bool = True,
                 baro_sigma_m: float = 1.0):
        self.surface = bool(surface)
        super().__init__(terrain, likelihood)
        if not (np.isfinite(baro_sigma_m) and baro_sigma_m > 0):
            raise FilterError(f"baro_sigma_m must be a positive number of metres, got {baro_sigma_m!r}")
        self.use_baro = bool(use_baro)
        self.baro_sigma_m = float(baro_sigma_m)
        self._kernel_chol: wp.array | None = None
        self._zero_kernel: wp.array | None = None

    @property
    def absorbs_map_offset(self) -> bool:
        return not self.use_baro

    @staticmethod
    def _m_of(items) -> int:
        return 1

    @staticmethod
    def _staging_buffer(device, b, m):
        return wp.empty(b, dtype=wp.vec4, device=device)

    def _fill(self, items, meta: wp.array) -> np.ndarray:
        """The readings into the staged rows and ``meta``; returns 1 for each valid reading."""
        rng_m = np.array([r.range_m for r in items], dtype=np.float64)
        baro = np.array([r.baro_alt_m for r in items], dtype=np.float64)
        valid = np.array([r.valid for r in items]) & np.logical_or(not self.use_baro, np.isfinite(baro))
        host = np.stack([np.where(valid, rng_m, 0.0), np.where(np.isfinite(baro), baro, 0.0), valid,
                         np.full(len(items), 1.0 / self.baro_sigma_m**2)], axis=1)
        self._uploads.put("readings", self._staged, host)
        n_received = valid.astype(np.int64)
        self._uploads.put("meta", meta, self._meta(n_received))
        return n_received

    def bind_particle_kernel(self, chol: wp.array | None) -> None:
        """Score each particle for its regularisation kernel: ``chol`` ((B,) mat33 on the particles' device, m: each
        filter's kernel factor, kept current by its owner, :class:`~warptan.filter.mpf.MarginalizedParticleFilter`); the
        residual's σ grows by the map's height variance over the kernel
        (:func:`warptan.kernels.sliding.kernel_height`). None (the default): point particles."""
        if chol is not self._kernel_chol:
            self._kernel_chol = chol
            self.generation += 1

    def _particle_kernel(self, device, b: int) -> wp.array:
        return self._bound_or_zero(self._kernel_chol, "_zero_kernel", device, b)

    def _launch(self, pos_n, quat_nb, out, device):
        mean, var = self._mode_state(device, pos_n.shape[0], self.n_filters)
        launch(kslide.altimeter_loglik_kernel, dim=pos_n.shape[0],
                  inputs=[self.n_per, self.terrain.grid(device), int(self.surface), int(self.use_baro), pos_n,
                          self._staged, self._params, self._modes, mean, var,
                          self._particle_kernel(device, self.n_filters)],
                  outputs=[out.residual_m, out.error_m, out.loglik, out.nis, out.n_valid, out.lam, out.info,
                           out.mode_post, out.info_pos],
                  device=device)


MODELS = {"raycast": RaycastModel, "sliding": SlidingModel, "altimeter": AltimeterModel}


def make_model(name: str, terrain, likelihood: Likelihood | None = None, backend: str = "dda",
               **kwargs) -> MeasurementModel:
    """Build a model by name ("raycast", "sliding", "altimeter"); ``backend`` applies to raycast."""
    if name not in MODELS:
        raise FilterError(f"unknown measurement model {name!r}; choose one of {', '.join(MODELS)}")
    if name == "raycast":
        kwargs.setdefault("caster", RayCaster(backend))
    return MODELS[name](terrain, likelihood, **kwargs)
