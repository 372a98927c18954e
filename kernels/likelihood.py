"""Per-particle reduction of residuals into the paper's scalar error and a log-likelihood (SPEC §5).

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
  - ``LIK_GAUSS``: ``sum_j -0.5 (res_ij / sigma)^2`` over the received valid points;
  - ``LIK_STUDENT``: ``sum_j -(nu+1)/2 log(1 + res_ij^2 / (nu sigma^2))``.
  In the per-point forms a received point whose prediction is invalid scores as a residual of
  ``k_out`` sigma, so that every particle sums the same number of terms (constants dropped).
If no received point is valid at all, every particle gets 0 (no information) and the caller flags it.

* the normalised squared residual ``nis_i = (Σ_j min((res_ij/σ)^2, k_out^2) + (n_recv - n_ok) k_out^2) / n_recv``
  (dimensionless, about 1 for a particle at the true pose when σ is the residuals' true scale, at most
  ``k_out^2``: one occluded ray cannot dominate it), whatever the likelihood: the integrity monitor of the
  filter uses it (:mod:`warptan.kernels.mpf`).
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
    """Empty running sums: received points, valid predictions, Σ|r|, Σ|r| |d|, last r, Σ point log-densities,
    Σ (r/σ)²."""
    return int(0), int(0), float(0.0), wp.vec3(), float(0.0), float(0.0), float(0.0)


@wp.func
def acc_add(n_ok: int, sum_abs: float, sum_axes: wp.vec3, last: float, ll_points: float, sum_sq: float,
            p: LikParams, res: float, axis_w: wp.vec3):
    """Running sums over the valid predictions of one particle: add one residual (m, finite)."""
    a = wp.abs(res)
    z = res / p.sigma
    return (n_ok + 1, sum_abs + a, sum_axes + a * axis_w, res, ll_points + point_loglik(p.lik, res, p.sigma, p.nu),
            sum_sq + wp.min(z * z, p.k_out * p.k_out))


@wp.func
def acc_finish(n_recv: int, n_ok: int, sum_abs: float, sum_axes: wp.vec3, last: float, ll_points: float,
               sum_sq: float, p: LikParams):
    """(paper error in m — NaN without a valid point, log-likelihood, normalised squared residual) of a particle
    that could predict ``n_ok`` of the ``n_recv`` received valid points; each unpredictable one scores the floor
    (a ``k_out`` σ residual; see the module docstring for the paper form)."""
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
    nis = float(0.0)
    if n_recv > 0:
        n_bad = float(n_recv - n_ok)
        floor = -0.5 * p.k_out * p.k_out
        if p.lik == LIK_PAPER:
            ll = floor
            if n_ok > 0:
                frac = float(n_ok) / float(n_recv)
                ll = frac * (-0.5 * err * err / p.r_err) + (1.0 - frac) * floor
        else:
            ll = ll_points + n_bad * point_loglik(p.lik, p.k_out * p.sigma, p.sigma, p.nu)
        nis = (sum_sq + n_bad * p.k_out * p.k_out) / float(n_recv)
    return err, ll, nis


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
    nis_out: wp.array(dtype=wp.float32),
    n_valid_out: wp.array(dtype=wp.int32),
):
    """One thread per particle (global index ``row0 + t``): paper error (m), log-likelihood, normalised squared
    residual, usable points."""
    t = wp.tid()
    b = (row0 + t) // n_per
    n_recv, n_ok, sum_abs, sum_axes, last, llp, ssq = acc_init()
    for j in range(residual.shape[1]):
        row = cloud[b, j]
        res = residual[t, j]
        if row[7] != 0.0:
            n_recv += 1
            if not wp.isnan(res):
                n_ok, sum_abs, sum_axes, last, llp, ssq = acc_add(n_ok, sum_abs, sum_axes, last, llp, ssq, params,
                                                                  res, axis_weights(row))
    err, ll, nis = acc_finish(n_recv, n_ok, sum_abs, sum_axes, last, llp, ssq, params)
    err_out[t] = err
    loglik_out[t] = ll
    nis_out[t] = nis
    n_valid_out[t] = n_ok
