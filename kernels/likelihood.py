"""Per-particle reduction of residuals into the paper's scalar error and a log-likelihood (SPEC §5).

Input: an (N, M) array of residuals (m, NaN = the particle's prediction for point j is invalid), and per
point j a flag that the *received* point is valid and a vector of axis weights. Output per particle i:

* the paper's error ``err_i``:
  - ``ERR_AXES`` (ray casting, eq. 15): ``sqrt(sum_axis (mean_j |res_ij| w_j,axis)^2)`` with
    ``w_j = |d_j|`` per axis, since ``c_j - c^_ij = (r_j - t_ij) d_j``;
  - ``ERR_MEAN_ABS`` (sliding, eq. 16): ``mean_j |res_ij|``;
  - ``ERR_SIGNED`` (altimeter, eq. 17): the single residual;
* the log-likelihood:
  - ``LIK_PAPER``: ``-0.5 err_i^2 / r_err``; a particle with no valid point gets ``-0.5 k_out^2``;
  - ``LIK_GAUSS``: ``sum_j -0.5 (res_ij / sigma)^2`` over the received valid points;
  - ``LIK_STUDENT``: ``sum_j -(nu+1)/2 log(1 + res_ij^2 / (nu sigma^2))``.
  In the per-point forms a received point whose prediction is invalid scores as a residual of
  ``k_out`` sigma, so that every particle sums the same number of terms (constants dropped).
If no received point is valid at all, every particle gets 0 (no information) and the caller flags it.
One thread per particle loops over the M points (:func:`acc_add` per valid prediction, :func:`acc_finish`), either over
an (N, M) residual array (:func:`reduce_loglik_kernel`) or fused with the prediction (the sliding model).

Filters in a batch: particle i belongs to filter ``b = i // n_per`` and reads the received measurement
``cloud[b, :]``, rows of ``CLOUD_FIELDS`` float32 ``[c (3), d (3), range, ok]`` (point, unit direction,
measured range, 1 = valid point).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

ERR_AXES = wp.constant(0)
ERR_MEAN_ABS = wp.constant(1)
ERR_SIGNED = wp.constant(2)
LIK_PAPER = wp.constant(0)
LIK_GAUSS = wp.constant(1)
LIK_STUDENT = wp.constant(2)


cloud_row = wp.types.vector(length=8, dtype=wp.float32)
"""One received point: [c_x, c_y, c_z (m), d_x, d_y, d_z, range (m), ok (1 or 0)]."""


@wp.struct
class LikParams:
    """How residuals become a log-likelihood (see the module docstring)."""

    err_kind: int
    lik: int
    r_err: float
    sigma: float
    nu: float
    k_out: float


@wp.func
def point_loglik(lik: int, res: float, sigma: float, nu: float) -> float:
    """Log density (constants dropped) of one residual under the per-point model."""
    z2 = (res / sigma) * (res / sigma)
    if lik == LIK_STUDENT:
        return -0.5 * (nu + 1.0) * wp.log(1.0 + z2 / nu)
    return -0.5 * z2


@wp.func
def acc_init():
    """Empty running sums: received points, valid predictions, Σ|r|, Σ|r| |d|, last r, Σ point log-densities."""
    return int(0), int(0), float(0.0), wp.vec3(), float(0.0), float(0.0)


@wp.func
def acc_add(n_ok: int, sum_abs: float, sum_axes: wp.vec3, last: float, ll_points: float, p: LikParams, res: float,
            axis_w: wp.vec3):
    """Running sums over the valid predictions of one particle: add one residual (m, finite)."""
    a = wp.abs(res)
    return n_ok + 1, sum_abs + a, sum_axes + a * axis_w, res, ll_points + point_loglik(p.lik, res, p.sigma, p.nu)


@wp.func
def acc_finish(n_recv: int, n_ok: int, sum_abs: float, sum_axes: wp.vec3, last: float, ll_points: float,
               p: LikParams):
    """(paper error in m — NaN without a valid point, log-likelihood) of a particle that could predict ``n_ok``
    of the ``n_recv`` received valid points; each unpredictable one scores as a ``k_out`` σ residual."""
    err = float(wp.nan)
    if n_ok > 0:
        inv = 1.0 / float(n_ok)
        if p.err_kind == ERR_AXES:
            err = wp.length(sum_axes * inv)
        elif p.err_kind == ERR_MEAN_ABS:
            err = sum_abs * inv
        else:
            err = last
    ll = float(0.0)
    if n_recv > 0:
        if p.lik == LIK_PAPER:
            if n_ok > 0:
                ll = -0.5 * err * err / p.r_err
            else:
                ll = -0.5 * p.k_out * p.k_out
        else:
            ll = ll_points + float(n_recv - n_ok) * point_loglik(p.lik, p.k_out * p.sigma, p.sigma, p.nu)
    return err, ll


@wp.func
def axis_weights(row: cloud_row) -> wp.vec3:
    """|d_j| per axis: the weights of the paper's per-axis error (eq. 15)."""
    return wp.vec3(wp.abs(row[3]), wp.abs(row[4]), wp.abs(row[5]))


@wp.kernel
def reduce_loglik_kernel(
    row0: int,
    n_per: int,
    residual: wp.array2d(dtype=wp.float32),
    cloud: wp.array2d(dtype=cloud_row),
    params: LikParams,
    err_out: wp.array(dtype=wp.float32),
    loglik_out: wp.array(dtype=wp.float32),
    n_valid_out: wp.array(dtype=wp.int32),
):
    """One thread per particle (global index ``row0 + t``): paper error (m), log-likelihood, usable points."""
    t = wp.tid()
    b = (row0 + t) // n_per
    n_recv, n_ok, sum_abs, sum_axes, last, llp = acc_init()
    for j in range(residual.shape[1]):
        row = cloud[b, j]
        res = residual[t, j]
        if row[7] != 0.0:
            n_recv += 1
            if not wp.isnan(res):
                n_ok, sum_abs, sum_axes, last, llp = acc_add(n_ok, sum_abs, sum_axes, last, llp, params, res,
                                                             axis_weights(row))
    err, ll = acc_finish(n_recv, n_ok, sum_abs, sum_axes, last, llp, params)
    err_out[t] = err
    loglik_out[t] = ll
    n_valid_out[t] = n_ok
