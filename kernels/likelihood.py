# Over 500 lines on purpose: the per-point accumulators (Acc, ModeAcc) and their init, add, pack, unpack, block sum
# and finish are one unit (a field added to Acc touches each of them) compiled into every likelihood kernel.
"""Per-particle reduction of residuals into the paper's scalar error and a log-likelihood (design notes §5).

Input: an (N, M) array of residuals (m, NaN = the particle's prediction for point j is invalid), and per
point j a flag that the *received* point is valid and a vector of axis weights. Output per particle i:

* the paper's error ``err_i``:
  - ``ERR_AXES`` (ray casting, eq. 15): ``sqrt(sum_axis (mean_j |res_ij| w_j,axis)^2)`` with
    ``w_j = |d_j|`` per axis, since ``c_j - c^_ij = (r_j - t_ij) d_j``;
  - ``ERR_MEAN_ABS`` (sliding, eq. 16): ``mean_j |res_ij|``;
  - ``ERR_SIGNED`` (altimeter, eq. 17): the single residual;
* the log-likelihood:
  - ``LIK_PAPER``: ``-0.5 err_i^2 / r_err`` over the points the particle can predict, blended with the floor
    ``-0.5 k_out^2`` by the fraction of received points it cannot predict (off the map, nodata, no hit):
    ``ll = (n_ok/n_recv)(-0.5 err^2/r_err) + (1 - n_ok/n_recv)(-0.5 k_out^2)``, so that a particle over a hole
    or off the map is never rewarded for predicting fewer points;
  - ``LIK_GAUSS``: ``sum_j -0.5 (res_ij / sigma)^2`` over the received valid points, marginalised over the
    particle's attitude uncertainty (its Kalman covariance ``A`` of dθ): with ``H_ij`` the Jacobian of the
    prediction w.r.t. dθ (``res ≈ H δθ + e``), ``Λ = Σ Hᵀ H / σ²``, ``b = Σ Hᵀ r / σ²``, it adds
    ``0.5 bᵀ A (I + ΛA)⁻¹ b - 0.5 log det(I + AΛ)`` (the log of ``N(r; 0, H A Hᵀ + σ² I)`` up to a constant,
    design notes §6b). Without it the attitude error the filter cannot see biases the position: the position absorbs
    the residual pattern a tilt or yaw causes;
  - ``LIK_STUDENT``: ``sum_j -(nu+1)/2 log(1 + res_ij^2 / (nu sigma^2))``, marginalised the same way with
    each point's precision the Student-t's iteratively-reweighted one, ``(nu+1)/(nu + (res/σ)²) / σ²`` (a
    Laplace approximation: an outlying point informs neither the weight nor the attitude).
* the information a particle's residuals carry on its attitude error, ``Λ_i`` (3×3, rad⁻²) and ``b_i`` (3,
  rad⁻¹) as above (per-point precision ``1/σ²``, the Student-t's reweighted one for ``LIK_STUDENT``), times
  ``att_scale = (σ/σ_att)²`` (the map error persists over a scan's footprint:
  :class:`warptan.sensing.likelihood.Likelihood`): the Kalman measurement update of the linear states
  (:mod:`warptan.kernels.mpf`) reads them. Zero for ``LIK_PAPER``: its scalar error is not a model of the points, and
  the paper's filter has C = 0 (a Kalman update from residuals whose weights do not follow them fed a lost filter's
  misfit into its attitude). In the per-point forms a received point whose prediction is invalid scores as a residual of
  ``k_out`` sigma, so that every particle sums the same number of terms (constants dropped).
If no received point is valid at all, every particle gets 0 (no information) and the caller flags it.

* the normalised squared residual ``nis_i = (Σ_j min((res_ij/σ)^2, k_out^2) + (n_recv - n_ok) k_out^2) / n_recv``
  (dimensionless, about 1 for a particle at the true pose when σ is the residuals' true scale, at most
  ``k_out^2``: one occluded ray cannot dominate it; told that the map is not the world, a gross miss counts its
  point's ``min(z_v, k_out)^2``, :func:`acc_gated`), whatever the likelihood: the integrity monitor of the filter
  uses it (:mod:`warptan.kernels.mpf`).
On CUDA one block of ``BLOCK_DIM`` threads per particle (``wp.launch_tiled``): each lane sums every
``BLOCK_DIM``-th point (:func:`acc_add` per valid prediction), the lanes' sums are added with one tile reduction
(:func:`acc_block_sum`) and the particle is finished once (:func:`acc_finish`), either over an (N, M) residual
array (:data:`reduce_loglik_kernels`) or fused with the prediction (the sliding model). On the CPU one thread per
particle loops over the points in order (the same kernel source without the block, :func:`per_particle_kernels`).
Measured on an H100 (N = 500, M = 400, per-point Gaussian, ``scripts/profile_filter_step.py``): one thread per
particle took 205 µs per reduction (sliding, fused with the map reads: 512 µs): 500 threads cannot hide the
latency of strided loads.

Filters in a batch: particle i belongs to filter ``b = i // n_per`` and reads the received measurement
``cloud[b, :]``, rows of ``CLOUD_FIELDS`` float32 ``[c (3), d (3), range, ok]`` (point, unit direction,
measured range, 1 = valid point).
"""

import warp as wp

from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.terrain import is_nan

wp.set_module_options({"enable_backward": False})

ERR_AXES = wp.constant(0)
ERR_MEAN_ABS = wp.constant(1)
ERR_SIGNED = wp.constant(2)
LIK_PAPER = wp.constant(0)
LIK_GAUSS = wp.constant(1)
LIK_STUDENT = wp.constant(2)


MAX_MODES = 16
"""Most map-error modes a likelihood marginalises (:class:`warptan.sensing.likelihood.Likelihood`, stated DEM
accuracy)."""
modes_vec = wp.types.vector(length=MAX_MODES, dtype=wp.float32)
"""One point's row of the map-error mode table, ``u_ji`` for mode i (zero past the modes in use); after the M points'
rows (at ``M + MODE_*``) the modes' one-scan prior variances ``k⁰_i``, their one-scan weights ``c⁰_i`` (the NIS),
their along-track correlations ``ρ_i``, the attitude information's weights ``cᵃ_i`` and the basis change ``T``
(``MAX_MODES`` rows) from the previous table's modes (:meth:`warptan.sensing.likelihood.Likelihood.error_modes`); also
a particle's mode amplitudes (whitened) and a filter's variances of them."""
MODE_K0 = 0
"""Row ``M + MODE_K0`` of the mode table: ``k⁰_i = σ_e² λ_i / σ²``, a mode's variance in one scan (whitened)."""
MODE_C0 = 1
"""Row ``M + MODE_C0``: ``c⁰_i = k⁰_i / (1 + k⁰_i)``, the NIS's one-scan weights."""
MODE_RHO = 2
"""Row ``M + MODE_RHO``: ``ρ_i``, a mode amplitude's correlation from one scan to the next (first-order model)."""
MODE_CA = 3
"""Row ``M + MODE_CA``: ``cᵃ_i = κᵃ_i k⁰_i / (1 + κᵃ_i k⁰_i)``, the attitude information's weights (a mode's error
counted once per κᵃ_i scans that share it, :meth:`warptan.sensing.likelihood.Likelihood.error_modes`;
:func:`attitude_information`)."""
MODE_T = 4
"""Rows ``M + MODE_T + i``: the new mode i's coefficients on the previous table's modes (identity when the table was
not rebuilt since the last scan, zero when there was none: nothing to carry)."""
MODE_EXTRA_ROWS = MODE_T + MAX_MODES
"""Rows of the mode table after the M points' rows."""
modes_mat = wp.types.matrix(shape=(MAX_MODES, 3), dtype=wp.float32)
"""Per mode, ``Σ_j v_ji H_j / σ_j`` (or ``G_j``): the Jacobians seen through the modes."""

cloud_row = wp.types.vector(length=8, dtype=wp.float32)
"""One received point: [c_x, c_y, c_z (m), d_x, d_y, d_z, range (m), ok (1 or 0)] (indices below)."""
CR_POINT = wp.constant(0)  # 3 values: the point in the sensor frame, m (0 where invalid)
CR_DIR = wp.constant(3)  # 3 values: the unit ray direction in the sensor frame
CR_RANGE = wp.constant(6)  # the range along the ray, m (NaN where invalid)
CR_VALID = wp.constant(7)  # 1: a valid sample, 0: not
CLOUD_ROW_LEN = 8

META_RECEIVED = wp.constant(0)
"""Column of a model's per-filter ``meta`` (B, 2): the number of valid received points."""
META_FLOOR = wp.constant(1)
"""Column of ``meta``: the log-likelihood floor for a particle whose value is not finite."""
CLOUD_META_COLS = wp.constant(2)
"""Columns of ``meta``, which a point cloud's upload carries after its ranges (:data:`cloud_rows_kernel`)."""


@wp.func
def row_point(row: cloud_row) -> wp.vec3:
    return wp.vec3(row[CR_POINT], row[CR_POINT + 1], row[CR_POINT + 2])


@wp.func
def row_dir(row: cloud_row) -> wp.vec3:
    return wp.vec3(row[CR_DIR], row[CR_DIR + 1], row[CR_DIR + 2])


@wp.kernel
def cloud_rows_kernel(ranges: wp.array2d(dtype=wp.float32), dirs: wp.array2d(dtype=wp.vec3),
                      rows_out: wp.array2d(dtype=cloud_row), meta_out: wp.array2d(dtype=wp.float32)):
    """Filter f's point j as its row of the staged cloud from its range (m, NaN = invalid) and its unit direction
    (``dirs`` (1, M): one pattern shared by every filter; (B, M): one per filter): the point ``r d`` (0 where
    invalid), ``d``, ``r``, valid; point 0 also copies the filter's meta row, which follows its M ranges
    (:data:`CLOUD_META_COLS` columns). The host uploads the ranges and meta only, as one copy (a batch of 100 clouds
    of 400 points built its rows with NumPy in 1 ms; the meta's copy of its own was a graph node, ~2 µs)."""
    f, j = wp.tid()
    d = dirs[wp.min(f, dirs.shape[0] - 1), j]
    r = ranges[f, j]
    ok = r == r
    c = wp.vec3()
    if ok:
        c = d * r
    rows_out[f, j] = cloud_row(c[0], c[1], c[2], d[0], d[1], d[2], r, wp.where(ok, 1.0, 0.0))
    if j == 0:
        m = rows_out.shape[1]
        for k in range(CLOUD_META_COLS):
            meta_out[f, k] = ranges[f, m + k]


@wp.struct
class LikParams:
    """How residuals become a log-likelihood (see the module docstring)."""

    err_kind: int
    lik: int
    r_err: float
    sigma: float
    nu: float
    k_out: float
    att_scale: float  # (σ / σ_att)² ≤ 1: the share of Λ, b the Kalman update of the attitude may use
    pos_precision: float  # prior precision of the position (m⁻²) in the Schur complement; < 0: no projection
    sigma_range: float  # the sensor's range σ, m (the sliding model's per-point σ)
    sigma_map: float  # the vertical map part of σ, m (σ² = sigma_range² + sigma_map² for a nadir point)
    n_modes: int  # map-error modes marginalised (0: none)
    sigma_err: float  # the stated correlated map error's RMS, m, where the modes do not hold it (0: none)


@wp.func
def point_loglik_z2(lik: int, z2: float, nu: float) -> float:
    """Log density (constants dropped) of one residual of squared whitened size ``z² = r² / σ²`` under the per-point
    model (less ``log σ``)."""
    if lik == LIK_STUDENT:
        return -0.5 * (nu + 1.0) * wp.log(1.0 + z2 / nu)
    return -0.5 * z2


@wp.func
def point_loglik(lik: int, res: float, sigma: float, nu: float) -> float:
    """Log density (constants dropped) of one residual under the per-point model."""
    return point_loglik_z2(lik, (res / sigma) * (res / sigma), nu)


VAR_RATIO_FOLD_MIN = wp.constant(1.0e-12)
VAR_RATIO_FOLD_MAX = wp.constant(1.0e12)
"""Bounds of :attr:`Acc.var_ratio` outside which :func:`acc_add` folds its log into the sums (float32 keeps ratios
of per-point σs to ~1e±26 more without overflow or subnormals)."""


@wp.struct
class Acc:
    """Running sums over the received points of one particle."""

    n_recv: int  # received valid points
    n_ok: int  # of them, predictable by the particle
    sum_abs: float  # Σ|r|, m
    sum_axes: wp.vec3  # Σ|r| |d| per axis, m
    last: float  # the last residual, m
    ll_points: float  # Σ point log-densities, less half the log of ``var_ratio`` (:func:`acc_ll_points`)
    var_ratio: float  # Π σ_j² / σ² over the points since it was last folded into ``ll_points`` (:func:`acc_add`)
    sum_sq: float  # Σ min((r/σ)², k_out²)
    lam: wp.mat33  # Λ = Σ Hᵀ H / σ² (H: the prediction's Jacobian w.r.t. the attitude error dθ, m/rad)
    info: wp.vec3  # b = Σ Hᵀ r / σ²
    lam_pp: wp.mat33  # Σ G Gᵀ / σ² (G: the prediction's Jacobian w.r.t. the position, 1)
    lam_tp: wp.mat33  # Σ H Gᵀ / σ², m/rad
    info_p: wp.vec3  # Σ Gᵀ r / σ², 1/m
    sq_raw: float  # Σ z² unclipped (the NIS's Mahalanobis form)
    n_gated: int  # of the predictable points, those dropped as gross misses (:func:`gross_miss`; not in n_ok)
    gated_ll: float  # Σ over the gross misses of their log-density (:func:`acc_gated`)
    gated_sq: float  # Σ over the gross misses of their min(z², k_out²) (:func:`acc_gated`)


@wp.struct
class ModeAcc:
    """The map-error modes' running sums and weights of one particle (touched only when modes are in use). Apart from
    :class:`Acc` because a loop-carried struct is copied at every point on the CPU: with these ~200 floats inside, the
    per-point ``acc = acc_point(acc, ...)`` copies made the CPU's sliding kernel 2.8× and the ray casts' reduction
    1.6× slower even where no mode is in use (map = world; S8 / S7, N = 500, 2 threads). The per-point sums now take
    both structs by reference (``wp.ref``: :func:`acc_point`, :func:`acc_modes`), which removes the copies that were
    left (the CPU stalled reading back each point's freshly stored ~180-byte :class:`Acc`): S8's sliding kernel
    20 → 25 M points/s, S7's reduction 9 → 14 (2 threads, same bits)."""

    proj: modes_vec  # per map-error mode i: p_i = Σ_j v_ji r_j / σ_j (v_ji: the table's row j)
    proj_h: modes_mat  # per mode: Σ_j v_ji H_j / σ_j
    proj_g: modes_mat  # per mode: Σ_j v_ji G_j / σ_j
    mode_w: modes_vec  # per mode: its gain c_i = P⁻_i / (1 + P⁻_i) (set after the sums by acc_set_modes)
    mode_q: modes_vec  # per mode: the amplitude's posterior mean q_i = μ_i + c_i (p_i − μ_i) (likewise)
    mode_mu: modes_vec  # per mode: the amplitude's prior mean μ_i (likewise)
    mode_w0: modes_vec  # per mode: its one-scan weight c⁰_i for the NIS (likewise)
    mode_wa: modes_vec  # per mode: the attitude information's weight (likewise)


@wp.func
def acc_init() -> Acc:
    """Empty running sums."""
    a = Acc()
    a.n_recv = 0
    a.n_ok = 0
    a.sum_abs = 0.0
    a.sum_axes = wp.vec3()
    a.last = 0.0
    a.ll_points = 0.0
    a.var_ratio = 1.0
    a.sum_sq = 0.0
    a.lam = wp.mat33()
    a.info = wp.vec3()
    a.lam_pp = wp.mat33()
    a.lam_tp = wp.mat33()
    a.info_p = wp.vec3()
    a.sq_raw = 0.0
    a.n_gated = 0
    a.gated_ll = 0.0
    a.gated_sq = 0.0
    return a


@wp.func
def modes_init() -> ModeAcc:
    """Empty mode sums."""
    m = ModeAcc()
    m.proj = modes_vec()
    m.proj_h = modes_mat()
    m.proj_g = modes_mat()
    m.mode_w = modes_vec()
    m.mode_q = modes_vec()
    m.mode_mu = modes_vec()
    m.mode_w0 = modes_vec()
    m.mode_wa = modes_vec()
    return m


@wp.func
def acc_modes(a: wp.ref[ModeAcc], p: LikParams, v: modes_vec, res: float, var: float, jac: wp.vec3,
              jac_pos: wp.vec3):
    """``a`` += one predictable point's projections on the map-error modes (its table row ``v``; called only when modes
    are in use; ``var`` = σ_j², m²): the whitened residual ``res / σ_j`` and the attitude and position Jacobians over
    ``σ_j`` (nothing for the paper's form). The rows are the scan's modes for its nominal sensitivities (a range's 1/cos
    of its angle from the vertical over flat ground): scaling them per particle by a ray's actual slope made them
    non-orthogonal, and the Woodbury with fixed weights then over-subtracted (Λ indefinite, S7 diverged).

    The gains ``c_i ≤ 1`` are the same for every particle of a filter: with the scan's orthonormal modes, Woodbury gives
    ``(I + Σ P_i u_i u_iᵀ)⁻¹ = I − Σ c_i u_i u_iᵀ``. A particle that predicts only some points keeps them: its modes are
    then not orthonormal, but ``c_i ≤ 1`` keeps ``Σ c_i p_i² ≤ zᵀz`` over its points (a principal block of a projector),
    so fewer points never score better. Renormalising each mode over the predicted points (``k_i / (1 + k_i |u_i|²)``)
    broke that bound: S5/S6 diverged onto particles that predict fewer points."""
    if p.lik != LIK_PAPER:
        inv = 1.0 / wp.sqrt(var)
        a.proj = a.proj + v * (res * inv)
        a.proj_h = a.proj_h + wp.outer(v, jac * inv)
        a.proj_g = a.proj_g + wp.outer(v, jac_pos * inv)


@wp.func
def mode_row(m: modes_mat, i: int) -> wp.vec3d:
    """Row ``i`` of a per-mode matrix in float64."""
    return wp.vec3d(wp.float64(m[i, 0]), wp.float64(m[i, 1]), wp.float64(m[i, 2]))


@wp.func
def upper_add(m: wp.ref[wp.mat33], a: wp.vec3, b: wp.vec3):
    """The upper triangle of ``m`` += ``outer(a, b)`` in place, ``a`` a multiple of ``b`` (the product symmetric;
    :func:`acc_symmetric` mirrors it)."""
    m[0, 0] = m[0, 0] + a[0] * b[0]
    m[0, 1] = m[0, 1] + a[0] * b[1]
    m[0, 2] = m[0, 2] + a[0] * b[2]
    m[1, 1] = m[1, 1] + a[1] * b[1]
    m[1, 2] = m[1, 2] + a[1] * b[2]
    m[2, 2] = m[2, 2] + a[2] * b[2]


@wp.func
def outer_add(m: wp.ref[wp.mat33], a: wp.vec3, b: wp.vec3):
    """``m += outer(a, b)`` in place."""
    for i in range(3):
        for j in range(3):
            m[i, j] = m[i, j] + a[i] * b[j]


@wp.func
def upper_mirrored(m: wp.mat33) -> wp.mat33:
    """``m`` with its lower triangle set from its upper one."""
    return wp.mat33(m[0, 0], m[0, 1], m[0, 2], m[0, 1], m[1, 1], m[1, 2], m[0, 2], m[1, 2], m[2, 2])


@wp.func
def acc_symmetric(a: Acc) -> Acc:
    """``a`` with Λ and Σ G Gᵀ / σ² made whole (:func:`acc_add` sums their upper triangles)."""
    s = a
    s.lam = upper_mirrored(a.lam)
    s.lam_pp = upper_mirrored(a.lam_pp)
    return s


@wp.func
def acc_add(a: wp.ref[Acc], p: LikParams, res: float, var: float, axis_w: wp.vec3, jac: wp.vec3, jac_pos: wp.vec3):
    """``a`` += one predictable residual ``res`` (m, finite) of variance ``var`` (m²; ``p.sigma²`` unless the model
    propagates the sensor's noise per point, which adds ``-log(σ_j / p.sigma)`` to the point's log-density), weighted
    by ``axis_w`` per axis for the paper's per-axis error, with ``jac`` the prediction's Jacobian w.r.t. dθ (m/rad)
    and ``jac_pos`` w.r.t. the position (dimensionless): ``min(z², k_out²)``, the point log-density, ``Hᵀ H / σ²``,
    ``Hᵀ r / σ²``, ``G Gᵀ / σ²``, ``H Gᵀ / σ²``, ``Gᵀ r / σ²`` (not the last five for the paper's form; the two
    symmetric ones by their upper triangles). In place, entry by entry (a matrix built per point and then added cost
    the CPU its copies), from the variance: no square root on the per-point path (it was the CPU sliding kernel's
    hottest instruction)."""
    inv_var = 1.0 / var
    z2 = res * res * inv_var
    r = wp.abs(res)
    a.n_ok = a.n_ok + 1
    a.sum_abs = a.sum_abs + r
    a.sum_axes = a.sum_axes + r * axis_w
    a.last = res
    a.sum_sq = a.sum_sq + wp.min(z2, p.k_out * p.k_out)
    a.sq_raw = a.sq_raw + z2
    a.ll_points = a.ll_points + point_loglik_z2(p.lik, z2, p.nu)
    var0 = p.sigma * p.sigma
    if var != var0:  # the density's -log(σ_j / σ), as one log per many points (a log per point cost 9 %)
        a.var_ratio = a.var_ratio * (var / var0)
        if not (a.var_ratio > VAR_RATIO_FOLD_MIN and a.var_ratio < VAR_RATIO_FOLD_MAX):
            a.ll_points = a.ll_points - 0.5 * wp.log(a.var_ratio)
            a.var_ratio = 1.0
    if p.lik != LIK_PAPER:  # the paper's scalar error is not a per-point model: its filter keeps C = 0
        w = inv_var
        if p.lik == LIK_STUDENT:  # the t's weight (ν + 1)/(ν + z²) on the information
            w = w * (p.nu + 1.0) / (p.nu + z2)
        h = jac * w
        g = jac_pos * w
        upper_add(a.lam, h, jac)
        a.info = a.info + h * res
        upper_add(a.lam_pp, g, jac_pos)
        outer_add(a.lam_tp, h, jac_pos)
        a.info_p = a.info_p + g * res


@wp.func
def acc_ll_points(a: Acc) -> float:
    """Σ point log-densities, ``-log(σ_j / σ)`` included."""
    return a.ll_points - 0.5 * wp.log(a.var_ratio)


ACC_BASE = 36
ACC_LEN = ACC_BASE + 4
acc_vec = wp.types.vector(length=ACC_LEN, dtype=wp.float32)
"""An :class:`Acc` as one vector (n_recv, n_ok, Σ|r|, Σ|r||d| (3), last, Σ log-density, Σ min(z², k²), Λ (6: 00 11
22 01 02 12), b (3), Σ GGᵀ (6), Σ HGᵀ (9, row-major), Σ G r (3), the gross misses' log-density and min(z², k²),
gross misses, Σ z²) for the block reduction. Counts are exact in float32 up to 2^24 points; ``last`` is the sum of
the lanes' last residuals, the residual itself for the one-point measurement that uses it."""
MODES_LEN = 7 * MAX_MODES
modes_sums_vec = wp.types.vector(length=MODES_LEN, dtype=wp.float32)
"""A :class:`ModeAcc`'s sums as one vector (p_i, then Σ v H / σ and Σ v G / σ row-major), reduced apart from
:data:`acc_vec` and only by the kernels with modes: in one vector with them, the block reduction of every
particle moved 152 floats a lane where 40 are in use without a stated map error."""

BLOCK_DIM = 64
"""Threads per particle in the block-reduced likelihood kernels (CUDA; a CPU block is one thread)."""


@wp.func
def acc_pack(a: Acc) -> acc_vec:
    """The running sums as one vector (see :data:`acc_vec`)."""
    v = acc_vec()
    v[0] = float(a.n_recv)
    v[1] = float(a.n_ok)
    v[2] = a.sum_abs
    v[3] = a.sum_axes[0]
    v[4] = a.sum_axes[1]
    v[5] = a.sum_axes[2]
    v[6] = a.last
    v[7] = acc_ll_points(a)
    v[8] = a.sum_sq
    v[9] = a.lam[0, 0]
    v[10] = a.lam[1, 1]
    v[11] = a.lam[2, 2]
    v[12] = a.lam[0, 1]
    v[13] = a.lam[0, 2]
    v[14] = a.lam[1, 2]
    v[15] = a.info[0]
    v[16] = a.info[1]
    v[17] = a.info[2]
    v[18] = a.lam_pp[0, 0]
    v[19] = a.lam_pp[1, 1]
    v[20] = a.lam_pp[2, 2]
    v[21] = a.lam_pp[0, 1]
    v[22] = a.lam_pp[0, 2]
    v[23] = a.lam_pp[1, 2]
    for r in range(3):
        for c in range(3):
            v[24 + 3 * r + c] = a.lam_tp[r, c]
    v[33] = a.info_p[0]
    v[34] = a.info_p[1]
    v[35] = a.info_p[2]
    v[ACC_LEN - 4] = a.gated_ll
    v[ACC_LEN - 3] = a.gated_sq
    v[ACC_LEN - 2] = float(a.n_gated)
    v[ACC_LEN - 1] = a.sq_raw
    return v


@wp.func
def acc_unpack(v: acc_vec) -> Acc:
    """Inverse of :func:`acc_pack`, its :class:`Acc` (Λ is symmetric)."""
    a = Acc()
    a.n_recv = int(v[0])
    a.n_ok = int(v[1])
    a.sum_abs = v[2]
    a.sum_axes = wp.vec3(v[3], v[4], v[5])
    a.last = v[6]
    a.ll_points = v[7]
    a.var_ratio = 1.0
    a.sum_sq = v[8]
    a.lam = wp.mat33(v[9], v[12], v[13], v[12], v[10], v[14], v[13], v[14], v[11])
    a.info = wp.vec3(v[15], v[16], v[17])
    a.lam_pp = wp.mat33(v[18], v[21], v[22], v[21], v[19], v[23], v[22], v[23], v[20])
    a.lam_tp = wp.mat33(v[24], v[25], v[26], v[27], v[28], v[29], v[30], v[31], v[32])
    a.info_p = wp.vec3(v[33], v[34], v[35])
    a.gated_ll = v[ACC_LEN - 4]
    a.gated_sq = v[ACC_LEN - 3]
    a.n_gated = int(v[ACC_LEN - 2])
    a.sq_raw = v[ACC_LEN - 1]
    return a


@wp.func
def modes_pack(m: ModeAcc) -> modes_sums_vec:
    """The mode sums as one vector (see :data:`modes_sums_vec`)."""
    v = modes_sums_vec()
    for i in range(MAX_MODES):
        v[i] = m.proj[i]
        for c in range(3):
            v[MAX_MODES + 3 * i + c] = m.proj_h[i, c]
            v[4 * MAX_MODES + 3 * i + c] = m.proj_g[i, c]
    return v


@wp.func
def modes_unpack(v: modes_sums_vec) -> ModeAcc:
    """Inverse of :func:`modes_pack`, its :class:`ModeAcc` (the sums; weights zero)."""
    m = modes_init()
    proj = modes_vec()
    proj_h = modes_mat()
    proj_g = modes_mat()
    for i in range(MAX_MODES):
        proj[i] = v[i]
        for c in range(3):
            proj_h[i, c] = v[MAX_MODES + 3 * i + c]
            proj_g[i, c] = v[4 * MAX_MODES + 3 * i + c]
    m.proj = proj
    m.proj_h = proj_h
    m.proj_g = proj_g
    return m


@wp.func
def acc_block_total(a: Acc) -> Acc:
    """The sums of every lane of the block (cooperative: every lane must call it; each gets the total)."""
    total = wp.tile_sum(wp.tile(acc_pack(a), preserve_type=True))
    return acc_unpack(total[0])


@wp.func
def modes_block_total(m: ModeAcc) -> ModeAcc:
    """The mode sums of every lane of the block (cooperative, as :func:`acc_block_total`)."""
    total = wp.tile_sum(wp.tile(modes_pack(m), preserve_type=True))
    return modes_unpack(total[0])


@wp.func
def mode_prior(table: wp.array(dtype=modes_vec), m: int, mean: modes_vec, var: modes_vec):
    """A particle's prior ``(μ⁻, P⁻)`` of the scan's mode amplitudes from its stored mean ``mean`` and its filter's
    stored variances ``var`` (both in the modes of the table the last scan used; ``var < 0``: none yet, the one-scan
    prior ``(0, k⁰)``). A rebuilt table's basis change ``T`` carries them over: ``μ⁻ = T μ``, ``P⁻_i = Σ_j T_ij²
    P_j + (1 − Σ_j T_ij²) k⁰_i`` (what the old modes do not cover gets the one-scan prior; cross-covariances
    dropped)."""
    k0 = table[m + MODE_K0]
    mu = modes_vec()
    pv = modes_vec()
    fresh = var[0] < 0.0
    for i in range(MAX_MODES):
        t = table[m + MODE_T + i]
        s = float(0.0)
        cover = float(0.0)
        v = float(0.0)
        for j in range(MAX_MODES):
            tt = t[j] * t[j]
            s += t[j] * mean[j]
            cover += tt
            v += tt * var[j]
        if fresh:
            mu[i] = 0.0
            pv[i] = k0[i]
        else:
            mu[i] = s
            pv[i] = v + wp.max(1.0 - cover, 0.0) * k0[i]
    return mu, pv


@wp.func
def acc_set_modes(acc: ModeAcc, table: wp.array(dtype=modes_vec), m: int, mean: modes_vec,
                  var: modes_vec) -> ModeAcc:
    """``acc`` (its sums complete) with its map-error modes' prior and posterior (:func:`mode_prior`): the gains
    ``c_i = P⁻_i / (1 + P⁻_i)``, the prior means μ_i, the posterior means ``q_i = μ_i + c_i (p_i − μ_i)``, the
    one-scan weights ``c⁰_i`` and the attitude's ``cᵃ_i``."""
    a = acc
    mu, pv = mode_prior(table, m, mean, var)
    w = modes_vec()
    for i in range(MAX_MODES):
        w[i] = pv[i] / (1.0 + pv[i])
    a.mode_w = w
    a.mode_mu = mu
    a.mode_q = mu + wp.cw_mul(w, a.proj - mu)
    a.mode_w0 = table[m + MODE_C0]
    a.mode_wa = table[m + MODE_CA]
    return a


@wp.func
def mode_post(acc: ModeAcc, table: wp.array(dtype=modes_vec), m: int) -> modes_vec:
    """The particle's mode amplitudes predicted to the next scan, ``ρ_i q_i`` (what the filter stores)."""
    return wp.cw_mul(table[m + MODE_RHO], acc.mode_q)


@wp.func
def modes_lam_info_w(acc: Acc, macc: ModeAcc, w: modes_vec, q: modes_vec, n_modes: int):
    """(Λ, b) in float64 with the map-error modes counted: ``Hᵀ Σ⁻¹ H`` and ``Hᵀ Σ⁻¹ (z − U μ)`` for ``Σ = I + U P⁻
    Uᵀ`` (whitened; ``U`` the modes, ``μ`` their prior means), by Woodbury ``Λ - Σ_i c_i h_i h_iᵀ``, ``b - Σ_i h_i
    q_i`` with ``q_i = μ_i + c_i (p_i − μ_i)`` (:func:`acc_modes`, :func:`acc_set_modes`), ``c = w`` over the
    first ``n_modes`` (0: Λ and b as summed)."""
    lam = wp.mat33d(acc.lam)
    info = wp.vec3d(acc.info)
    for i in range(MAX_MODES):  # (unrolled: a loop over the runtime n_modes indexed the per-mode sums dynamically,
        # which put them in CUDA local memory; unrolled, S8's tiled sliding kernel took 37.6 µs a call, not 62.5)
        if i < n_modes:
            h = mode_row(macc.proj_h, i)
            lam = lam - wp.outer(h, h) * wp.float64(w[i])
            info = info - h * wp.float64(q[i])
    return lam, info


@wp.func
def modes_lam_info(acc: Acc, macc: ModeAcc, p: LikParams):
    """:func:`modes_lam_info_w` with the modes' gains and posterior means."""
    return modes_lam_info_w(acc, macc, macc.mode_w, macc.mode_q, p.n_modes)


@wp.func
def modes_lam_info_fixed(acc: Acc, macc: ModeAcc, w: modes_vec, p: LikParams):
    """:func:`modes_lam_info_w` with fixed weights ``w`` and no prior mean: the one-scan ``c⁰_i`` (the NIS), the
    attitude's ``cᵃ_i`` (:func:`attitude_information`)."""
    return modes_lam_info_w(acc, macc, w, wp.cw_mul(w, macc.proj), p.n_modes)


@wp.func
def attitude_quadratic(lam: wp.mat33d, info: wp.vec3d, att_cov: wp.mat33):
    """``(bᵀ A (I + ΛA)⁻¹ b, det(I + AΛ))`` in float64, ``(0, 0)`` when the determinant is not positive. Integrating
    the residuals' dependence on the attitude error, ``r ≈ H dθ + e`` with ``dθ ~ N(0, A)``, adds ``0.5 bᵀ A (I +
    ΛA)⁻¹ b - 0.5 log det(I + AΛ)`` to the per-point Gaussian log-likelihood (Woodbury and the determinant lemma;
    0 when A = 0), and the quadratic is the part of the whitened ``zᵀz`` the attitude explains (``zᵀ(I + H̃ A
    H̃ᵀ)⁻¹z = zᵀz − bᵀ A (I + ΛA)⁻¹ b``)."""
    am = wp.mat33d(att_cov)
    m = wp.identity(n=3, dtype=wp.float64) + lam * am
    det = wp.determinant(m)
    if not (det > wp.float64(0.0)):
        return wp.float64(0.0), wp.float64(0.0)
    return wp.dot(info, am * (wp.inverse(m) * info)), det


GATED_SHARE_LOW = wp.constant(0.2)
GATED_SHARE_HIGH = wp.constant(0.6)
"""The share of a particle's predicted points that are gross misses (:func:`gross_miss`) from which on its scan is
taken for a wrong pose rather than a few rays that met another surface, and the share at which fully
(:func:`gated_scale`)."""


@wp.func
def gated_scale(p: LikParams, n_gated: int, n_ok: int) -> float:
    """The factor on a particle's gross misses' log-densities (:func:`acc_gated`) under a stated map error: 1 while
    they are a few rays of its scan, rising linearly to ``1 + σ_e² / σ²`` (the gate's scale ``k_out sqrt(σ² + σ_e²)``
    over the point's σ) between :data:`GATED_SHARE_LOW` and :data:`GATED_SHARE_HIGH` of its predicted points.

    A gross miss scores at most ``k_out`` σ, while a residual just inside the gate scores ``k_out² (σ² + σ_e²) / (2
    σ²)``: with a stated error much larger than σ the likelihood fell and then rose again with a particle's distance,
    the particles whose every point is a gross miss outscoring those a few metres off. Measured on a map better than
    stated (S8, map = world, told 4 m / 1 km, σ = 0.5 m, the true pose's scan): 5 m low −6 162 nats, 20 m low −800;
    the filter's altitude ran to −120 m at 0 % coverage (`warptan run S8 --map-error-m 4 --map-error-corr-m 1000`:
    61.6 m). Scaling every gross miss (not only a majority) cost S5 (60° bank, 5 m / 1 km world of seed 1003 with
    sub-post relief, told 5 m / 1 km, seeds 0–2, 90 s, CPU) 6.7 → 8.7 m: its glancing rays that meet another surface
    at the true pose have a small σ and a large gain. Without a stated error the factor is 1."""
    if p.sigma_err <= 0.0 or n_gated == 0:
        return 1.0
    share = float(n_gated) / float(n_gated + n_ok)
    ramp = wp.clamp((share - GATED_SHARE_LOW) / (GATED_SHARE_HIGH - GATED_SHARE_LOW), 0.0, 1.0)
    return 1.0 + ramp * (p.sigma_err * p.sigma_err) / (p.sigma * p.sigma)


@wp.func
def acc_finish(acc: Acc, macc: ModeAcc, p: LikParams, att_cov: wp.mat33):
    """(paper error in m — NaN without a valid point, log-likelihood, normalised squared residual) of a particle
    that could predict ``n_ok`` of the ``n_recv`` received valid points; each unpredictable one scores the floor
    (a ``k_out`` σ residual; see the module docstring for the paper form). The per-point Gaussian is marginalised
    over the attitude uncertainty ``att_cov`` (the Kalman covariance of dθ), the Student-t likewise."""
    n_recv = acc.n_recv
    n_ok = acc.n_ok
    err = float(wp.nan)
    if n_ok > 0:
        inv = 1.0 / float(n_ok)
        if p.err_kind == ERR_AXES:
            err = wp.length(acc.sum_axes * inv)
        elif p.err_kind == ERR_MEAN_ABS:
            err = acc.sum_abs * inv
        else:
            err = acc.last
    ll = float(0.0)
    nis = float(0.0)
    sum_sq = acc.sum_sq
    if n_recv > 0:
        n_bad = float(n_recv - n_ok)
        floor = -0.5 * p.k_out * p.k_out
        if p.lik == LIK_PAPER:
            ll = floor
            if n_ok > 0:
                frac = float(n_ok) / float(n_recv)
                ll = frac * (-0.5 * err * err / p.r_err) + (1.0 - frac) * floor
        else:  # a gross miss scores its point's height above the map (:func:`acc_gated`), the rest the floor
            n_floor = n_bad - float(acc.n_gated)
            ll = acc_ll_points(acc) + n_floor * point_loglik(p.lik, p.k_out * p.sigma, p.sigma, p.nu) + acc.gated_ll
            ll = ll + (gated_scale(p, acc.n_gated, n_ok) - 1.0) * acc.gated_ll
            # the NIS asks whether this particle, with an attitude within the Kalman's uncertainty A and a map error
            # as stated, explains the scan: the Mahalanobis zᵀ(I + U K⁰ Uᵀ + H̃ A H̃ᵀ)⁻¹z of the unclipped z, with
            # the modes' one-scan weights c⁰_i (not shared along the track: a smooth misfit of tens of metres is
            # not a 5 m map error, however many scans share the modes), and no more than the clipped sum (a gross
            # outlier counts k_out² at most)
            mahal = acc.sq_raw
            if p.n_modes > 0:  # the modes' share: (z − Uμ)ᵀΣ⁻¹(z − Uμ) = zᵀz − Σ [p_i² − (1 − c_i)(p_i − μ_i)²]
                d = macc.proj - macc.mode_mu
                ll = ll + 0.5 * (wp.dot(macc.proj, macc.proj) - wp.dot(wp.cw_mul(modes_vec(1.0) - macc.mode_w, d), d))
                mahal = mahal - wp.dot(wp.cw_mul(macc.mode_w0, macc.proj), macc.proj)
            if n_ok > 0:  # the attitude marginal (Λ and b through the modes; unchanged without them)
                lam, info = modes_lam_info(acc, macc, p)
                quad, det = attitude_quadratic(lam, info, att_cov)
                if det > wp.float64(0.0):
                    ll = ll + float(wp.float64(0.5) * quad - wp.float64(0.5) * wp.log(det))
                if p.n_modes > 0:  # the NIS's one-scan weights
                    lam0, info0 = modes_lam_info_fixed(acc, macc, macc.mode_w0, p)
                    quad, det = attitude_quadratic(lam0, info0, att_cov)
                mahal = mahal - float(quad)
            sum_sq = wp.min(sum_sq, wp.max(mahal, 0.0))
            sum_sq = sum_sq + acc.gated_sq - float(acc.n_gated) * p.k_out * p.k_out
        nis = (sum_sq + n_bad * p.k_out * p.k_out) / float(n_recv)
    return err, ll, nis


@wp.func
def axis_weights(row: cloud_row) -> wp.vec3:
    """|d_j| per axis: the weights of the paper's per-axis error (eq. 15)."""
    d = row_dir(row)
    return wp.vec3(wp.abs(d[0]), wp.abs(d[1]), wp.abs(d[2]))


@wp.func
def attitude_information(acc: Acc, macc: ModeAcc, p: LikParams):
    """(Λ, b) the Kalman update of the attitude reads, times ``att_scale``: with ``pos_precision ≥ 0`` the part of
    the residuals' information on dθ that the position cannot explain, the Schur complement
    ``Λ - Λ_θp (Λ_pp + π I)⁻¹ Λ_pθ``, ``b - Λ_θp (Λ_pp + π I)⁻¹ b_p`` (float64).

    With map-error modes the attitude reads the scan through the modes with the weights ``cᵃ_i = κᵃ_i k⁰_i / (1 + κᵃ_i
    k⁰_i)`` (``MODE_CA``), μ = 0: the Kalman update of dθ is made apart from the amplitudes' (no cross-covariance), and
    a mode's error is shared by the κᵃ_i consecutive scans that see the same ground (along the track as flown, turns
    included), so each scan may read only about 1/κᵃ_i of what one scan alone would say through it (κᵃ_i scans then hold
    what one independent patch holds: a map tilt read κᵃ_i times as independent is the tilt read as the attitude with a
    3σ √κᵃ_i too small). Measured (5 m / 1 km worlds, CPU): with the one-scan weights ``c⁰_i`` S8 over the world of seed
    1003 kept the roll 10 σ off and the east velocity 2.2 m/s off at 17 σ (east 3σ coverage 4–15 %, 6.0–6.6 m); with
    ``cᵃ`` 0.4–1.3 σ and 93–96 % (2.0–2.3 m). It needs the fix's wander in the Kalman part's position noise
    (:meth:`warptan.sensing.likelihood.Likelihood.fix_process`): without it S2's velocity ran away. Before
    (``results/world`` at 4397e95, 20 seeds, H100): the one-scan weights gave S7/S8 east coverage 68/60 %, the
    amplitudes' gains S2 7.7 m and S5 7.6 m, projecting every mode out of the attitude's information 250 m on S2 (the
    tactical IMU needs the attitude).
    """
    lam, info = modes_lam_info_fixed(acc, macc, macc.mode_wa, p)
    if p.pos_precision >= 0.0:
        lpp = wp.mat33d(acc.lam_pp) + wp.identity(n=3, dtype=wp.float64) * wp.float64(p.pos_precision)
        ltp = wp.mat33d(acc.lam_tp)
        info_p = wp.vec3d(acc.info_p)
        for i in range(MAX_MODES):  # the position's sums through the map-error modes likewise (unrolled, as in
            # modes_lam_info_w)
            if i < p.n_modes:
                h = mode_row(macc.proj_h, i)
                g = mode_row(macc.proj_g, i)
                wi = wp.float64(macc.mode_wa[i])
                lpp = lpp - wp.outer(g, g) * wi
                ltp = ltp - wp.outer(h, g) * wi
                info_p = info_p - g * (wi * wp.float64(macc.proj[i]))
        det = wp.determinant(lpp)
        if det > wp.float64(0.0):
            k = ltp * wp.inverse(lpp)
            lam = lam - k * wp.transpose(ltp)
            info = info - k * info_p
            lam = wp.float64(0.5) * (lam + wp.transpose(lam))
    s = wp.float64(p.att_scale)
    return wp.mat33(lam * s), wp.vec3(info * s)


@wp.func
def acc_store(t: int, acc: Acc, macc: ModeAcc, params: LikParams, att_cov: wp.mat33,
              err_out: wp.array(dtype=wp.float32),
              loglik_out: wp.array(dtype=wp.float32), nis_out: wp.array(dtype=wp.float32),
              n_valid_out: wp.array(dtype=wp.int32), lam_out: wp.array(dtype=wp.mat33),
              info_out: wp.array(dtype=wp.vec3)):
    """Finish particle ``t``'s sums (:func:`acc_finish`) and write its outputs."""
    whole = acc_symmetric(acc)
    err, ll, nis = acc_finish(whole, macc, params, att_cov)
    err_out[t] = err
    loglik_out[t] = ll
    nis_out[t] = nis
    n_valid_out[t] = acc.n_ok + acc.n_gated  # predictable (a gross miss was predicted, and scores the floor)
    lam, info = attitude_information(whole, macc, params)
    lam_out[t] = lam
    info_out[t] = info


@wp.func
def ray_jacobians(mat: wp.mat33, row: cloud_row, res: float, s: wp.vec3):
    """The predicted range's Jacobians w.r.t. dθ (m/rad) and the position (dimensionless) from the scaled normal
    ``s = ∇F / (∇F · u)`` at the hit (:func:`warptan.kernels.raycast.raycast_residual_kernel`): with the predicted
    range ``t = r - res`` and the ray ``d`` (sensor frame), ``t (Rᵀs) × d`` and ``-s``."""
    t = row[CR_RANGE] - res
    return t * wp.cross(wp.transpose(mat) * s, row_dir(row)), -s


RAY_MAP_GAIN_MAX = wp.constant(1000.0)
"""Range change per metre of map height a ray's σ counts at a grazing hit (``|∇F · u| ≤ 1e-3``, where the kernel
stores a zero scaled normal)."""


@wp.func
def ray_nominal_gain(u_down: float) -> float:
    """A range's change per metre of vertical map error over flat ground, ``1/u_z`` (``u_down``: the ray's down
    component, at least 0.1): the sensitivity the map-error modes use (:meth:`warptan.sensing.likelihood.Likelihood.
    error_modes` with the model's ``_scan_geometry``)."""
    return 1.0 / wp.max(u_down, 0.1)


@wp.func
def ray_var(p: LikParams, s: wp.vec3, u_down: float) -> float:
    """σ² of one range residual (m²): the range noise and a vertical map error ``δh``, which moves the predicted range
    by ``s_z δh`` (``s = ∇F / (∇F · u)`` the scaled normal, ``s_z = 1 / (∇F · u)``: 1 at nadir over flat ground,
    large where the ray meets the slope at a glancing angle): ``σ_j = sqrt(σ_range² + σ_map² s_z²)``. Not capped:
    the range's Jacobians grow with ``s`` as well (:func:`ray_jacobians`), so a ray along a slope carries no more
    information than its map error allows (capped like the sliding model's slope factor, a hill seen from a 60°
    bank gave S5 a 16° pitch error with a 3σ of 0.1° within ten seconds of the first attitude update). A stated
    correlated error (σ_e, ``sigma_err``) is held by the map-error modes with each ray's nominal sensitivity
    ``1/u_z`` (``u_down``: the ray's down component, at least 0.1;
    :meth:`warptan.sensing.likelihood.Likelihood.error_modes`); what the ray's own gain adds or lacks, ``(s_z − 1/u_z)
    e``, the modes cannot hold, and it is counted here as the ray's own: ``+ σ_e² (s_z − 1/u_z)²``. Without a map part
    (σ_map = 0 and no stated error: the map is the world) or with a fixed σ (σ_range = 0) it is the likelihood's own
    σ²."""
    if p.sigma_range <= 0.0 or (p.sigma_map <= 0.0 and p.sigma_err <= 0.0):
        return p.sigma * p.sigma
    gain = wp.float32(RAY_MAP_GAIN_MAX)
    if s[2] != 0.0:
        gain = wp.min(wp.abs(s[2]), gain)
    var = p.sigma_range * p.sigma_range + p.sigma_map * p.sigma_map * gain * gain
    if p.sigma_err > 0.0:
        excess = gain - ray_nominal_gain(u_down)
        var = var + p.sigma_err * p.sigma_err * excess * excess
    return var


@wp.func
def map_not_world(p: LikParams) -> bool:
    """The per-point likelihood is told its map is not the world: a stated correlated error (``sigma_err``) or a
    map σ of its own (``sigma_map``: post noise, interpolation or sub-post relief; 0 when the map is the world).
    Then a point the map cannot make is a gross miss (:func:`gross_miss`)."""
    return p.lik != LIK_PAPER and (p.sigma_err > 0.0 or p.sigma_map > 0.0)


@wp.func
def gross_miss(p: LikParams, res: float, var: float, gain: float) -> bool:
    """A point-cloud residual the map as stated cannot make: ``|res| > k_out sqrt(σ_j² + (σ_e gain)²)``, with ``σ_j² =
    var`` the point's own variance, ``σ_e`` the stated correlated map error (``sigma_err``, which the modes may hold)
    and ``gain`` the residual's change per metre of vertical map error (a range: ``1/u_z``, at most 10; a sliding
    height: 1). Only for the per-point forms told that the map is not the world (:func:`map_not_world`: a stated error,
    or a map σ of the map's own — without a stated error the Gaussian took a ray that met a sub-post bump the map lacks
    at full weight: S5 over a world with sub-post relief only, world 1002, seeds 10 and 0, CPU: north RMSE 1.15/1.07 m
    at 1.8/1.7 σ; gated 0.68/0.73 m at 0.8/0.9 σ). Such a residual is a ray that met another surface in the world than
    in the particle's map (it clears a ridge in one and meets it in the other; relief under the map's posts shadows it
    at a glancing angle): its size, tens to hundreds of metres, is not a Gaussian error, and the Gaussian gave the one
    or two such rays of a scan the whole weight (S5, the 60° bank whose rays reach the horizon, 5 m / 1 km world of seed
    1003, seed 15, CPU: the particles jumped 25–30 m north at the same place of every orbit with a 3σ of 2–6 m, 3σ
    coverage N/E 49/72 %; gated 75/92 %; ``results/world``, 20 seeds: 21.8 → 7.3 m, no seed lost; a world without the
    sub-post relief, 81/85 → 87/92 %, is another error field too: the world draws its error after its relief from one
    generator). It scores its point's height above the map (:func:`acc_gated`, at most the floor of a point the particle
    cannot predict) and adds nothing to the attitude's information or the modes."""
    if not map_not_world(p):
        return False
    e = p.sigma_err * gain
    return res * res > p.k_out * p.k_out * (var + e * e)


@wp.func
def acc_gated(a: wp.ref[Acc], p: LikParams, vertical: float, gain: float):
    """``a`` += a gross miss (:func:`gross_miss`) of a ray whose received point, placed with the particle's pose,
    lies ``vertical`` m above the map's surface (NaN: unknown, a sliding height). The ray met another surface in the
    world than in the map, so its range says nothing a Gaussian can use; but its point lies on the world's surface,
    which the map holds within the stated error: it scores ``min(z_v, k_out)`` σ with ``z_v = vertical / σ_v``,
    ``σ_v² = σ_e² + σ_map² + (σ_range / gain)²`` (the stated and the map's own vertical errors and the range noise
    along the ray's vertical, ``gain = 1/u_z``), at most the floor of a point the particle cannot predict. With
    the floor alone, a particle was paid for explaining the rays that grazed a ridge the world holds a few metres
    higher than the map: at the true pose such a ray passes over the map's ridge (a residual of −1.5 km), a
    particle 25 m off meets it (−50 to −100 m, within the gate), and three such rays gave that particle 12 nats
    (S5, world 1003, t = 50 s). The point's height above the map is near zero at either pose."""
    a.n_gated = a.n_gated + 1
    zc = p.k_out
    if not is_nan(vertical):
        var = p.sigma_err * p.sigma_err + p.sigma_map * p.sigma_map
        var = var + (p.sigma_range / gain) * (p.sigma_range / gain)
        zc = wp.min(wp.abs(vertical) / wp.sqrt(wp.max(var, 1.0e-12)), p.k_out)
    a.gated_ll = a.gated_ll + point_loglik(p.lik, zc * p.sigma, p.sigma, p.nu)
    a.gated_sq = a.gated_sq + zc * zc


@wp.func
def acc_point(a: wp.ref[Acc], p: LikParams, miss: bool, res: float, var: float, gain: float, vertical: float,
              axis_w: wp.vec3, jac: wp.vec3, jac_pos: wp.vec3):
    """``a`` += a point of a point cloud that the particle predicts (``var``: its σ_j², m²): a gross miss (``miss``:
    :func:`gross_miss`, ``gain`` its map-error sensitivity) scores its point's height above the map, ``vertical``
    (:func:`acc_gated`), else its sums (:func:`acc_add`); with modes the caller adds the other's projections on them
    (:func:`acc_modes`, the table's row of the point) to its :class:`ModeAcc`."""
    if miss:
        acc_gated(a, p, vertical, gain)
    else:
        acc_add(a, p, res, var, axis_w, jac, jac_pos)


def per_particle_kernels(make):
    """``{(tiled, modes): kernel}`` from ``make(tiled, modes)``: the block-reduced form for CUDA, the plain one for
    the CPU, whose launches :func:`warptan.parallel.launch_rows` splits across threads (Warp's CPU tile storage is one
    static buffer, which concurrent launches would share); ``modes``: with the map-error modes' sums
    (:class:`ModeAcc`), which a kernel without them does not carry through its loop over the points (the CPU copies a
    loop-carried struct at every point)."""
    return {(tiled, modes): make(tiled, modes) for tiled in (True, False) for modes in (True, False)}


def _reduce_loglik(tiled: bool, with_modes: bool):
    @wp.kernel
    def reduce_loglik_kernel(
        row0: int,
        n_per: int,
        residual: wp.array2d(dtype=wp.float32),
        quat_nb: wp.array(dtype=wp.vec4),
        normal: wp.array2d(dtype=wp.vec3),
        vertical: wp.array2d(dtype=wp.float32),
        cloud: wp.array2d(dtype=cloud_row),
        att_cov: wp.array(dtype=wp.mat33),
        params: LikParams,
        modes: wp.array(dtype=modes_vec),
        mode_mean: wp.array(dtype=modes_vec),
        mode_var: wp.array(dtype=modes_vec),
        err_out: wp.array(dtype=wp.float32),
        loglik_out: wp.array(dtype=wp.float32),
        nis_out: wp.array(dtype=wp.float32),
        n_valid_out: wp.array(dtype=wp.int32),
        lam_out: wp.array(dtype=wp.mat33),
        info_out: wp.array(dtype=wp.vec3),
        post_out: wp.array(dtype=modes_vec),
    ):
        """Particle ``t`` (global index ``row0 + t``; one block, or one thread): paper error (m), log-likelihood,
        normalised squared residual, usable points, attitude information Λ and b, map-error mode amplitudes for the
        next scan; ``normal[t, j]`` is the scaled surface normal at the hit (:func:`ray_jacobians`), ``vertical[t,
        j]`` the received point's height above the map (:func:`acc_gated`), ``att_cov[b]``
        the filter's attitude covariance, ``mode_mean[t]`` / ``mode_var[b]`` the modes' stored prior."""
        if wp.static(tiled):
            t, lane = wp.tid()
            stride = wp.block_dim()
        else:
            t = wp.tid()
            lane = 0
            stride = 1
        b = (row0 + t) // n_per
        mat = quat_to_mat_wxyz(quat_nb[t])
        acc = acc_init()
        macc = modes_init()
        for j in range(lane, residual.shape[1], stride):
            row = cloud[b, j]
            res = residual[t, j]
            if row[CR_VALID] != 0.0:
                acc.n_recv = acc.n_recv + 1
                if not is_nan(res):
                    s = normal[t, j]
                    jac, jac_pos = ray_jacobians(mat, row, res, s)
                    u_down = (mat * row_dir(row))[2]
                    var = ray_var(params, s, u_down)
                    vert = float(wp.nan)
                    if map_not_world(params):  # read only where a gross miss can be scored (acc_gated)
                        vert = vertical[t, j]
                    gain = ray_nominal_gain(u_down)
                    miss = gross_miss(params, res, var, gain)
                    acc_point(acc, params, miss, res, var, gain, vert, axis_weights(row), jac, jac_pos)
                    if wp.static(with_modes):
                        if not miss:
                            acc_modes(macc, params, modes[j], res, var, jac, jac_pos)
        if wp.static(tiled):
            acc = acc_block_total(acc)
            if wp.static(with_modes):
                macc = modes_block_total(macc)
        if lane == 0:
            if wp.static(with_modes):
                macc = acc_set_modes(macc, modes, residual.shape[1], mode_mean[t], mode_var[b])
                post_out[t] = mode_post(macc, modes, residual.shape[1])
            acc_store(t, acc, macc, params, att_cov[b], err_out, loglik_out, nis_out, n_valid_out, lam_out,
                      info_out)

    return reduce_loglik_kernel


reduce_loglik_kernels = per_particle_kernels(_reduce_loglik)
"""Per-particle reduction of an (N, M) residual array: ``[(True, modes)]`` tiled (``wp.launch_tiled``), ``[(False,
modes)]`` plain; ``modes``: with the map-error modes (a stated map error)."""
