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
One thread per particle loops over the M points.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})

ERR_AXES = wp.constant(0)
ERR_MEAN_ABS = wp.constant(1)
ERR_SIGNED = wp.constant(2)
LIK_PAPER = wp.constant(0)
LIK_GAUSS = wp.constant(1)
LIK_STUDENT = wp.constant(2)


@wp.func
def point_loglik(lik: int, res: float, sigma: float, nu: float) -> float:
    """Log density (constants dropped) of one residual under the per-point model."""
    z2 = (res / sigma) * (res / sigma)
    if lik == LIK_STUDENT:
        return -0.5 * (nu + 1.0) * wp.log(1.0 + z2 / nu)
    return -0.5 * z2


@wp.kernel
def reduce_loglik_kernel(
    residual: wp.array2d(dtype=wp.float32),
    point_ok: wp.array(dtype=wp.int32),
    axis_w: wp.array(dtype=wp.vec3),
    err_kind: int,
    lik: int,
    r_err: float,
    sigma: float,
    nu: float,
    k_out: float,
    err_out: wp.array(dtype=wp.float32),
    loglik_out: wp.array(dtype=wp.float32),
    n_valid_out: wp.array(dtype=wp.int32),
):
    """One thread per particle: paper error (m), log-likelihood, and the number of usable points."""
    i = wp.tid()
    m = residual.shape[1]
    n_ok = int(0)
    n_recv = int(0)
    sum_abs = float(0.0)
    sum_axes = wp.vec3(0.0, 0.0, 0.0)
    signed = float(0.0)
    ll_points = float(0.0)
    ll_out = point_loglik(lik, k_out * sigma, sigma, nu)
    for j in range(m):
        if point_ok[j] == 0:
            continue
        n_recv += 1
        res = residual[i, j]
        if wp.isnan(res):
            ll_points += ll_out
            continue
        n_ok += 1
        a = wp.abs(res)
        sum_abs += a
        sum_axes += a * axis_w[j]
        signed = res
        ll_points += point_loglik(lik, res, sigma, nu)
    err = float(wp.nan)
    if n_ok > 0:
        inv = 1.0 / float(n_ok)
        if err_kind == ERR_AXES:
            err = wp.length(sum_axes * inv)
        elif err_kind == ERR_MEAN_ABS:
            err = sum_abs * inv
        else:
            err = signed
    ll = float(0.0)
    if n_recv > 0:
        if lik == LIK_PAPER:
            if n_ok > 0:
                ll = -0.5 * err * err / r_err
            else:
                ll = -0.5 * k_out * k_out
        else:
            ll = ll_points
    err_out[i] = err
    loglik_out[i] = ll
    n_valid_out[i] = n_ok
