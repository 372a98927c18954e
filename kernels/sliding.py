"""Height-sampling measurement models: the sliding grid (paper eq. 14, 16) and the altimeter (eq. 8, 17).

No ray is cast. Sliding: each received point ``c_j`` (sensor frame) is placed with the hypothetical pose,
``w_ij = p_i + R_i c_j``; the map is read under it, ``w^_ij = (w_x, w_y, -h(w_x, w_y))``; the predicted
point is ``c^_ij = R_i^T (w^_ij - p_i)`` and the residual is ``c_j,z - c^_ij,z`` (m). Altimeter: the
predicted range is ``a^_i = h_baro - h(p_i,x, p_i,y)`` and the residual ``a - a^_i`` (m).
A point or particle off the map, on nodata, or with a NaN input gives a NaN residual (excluded later).

The sliding kernel is fused: on CUDA one block per particle (``wp.launch_tiled``), each lane reads the map under
every ``BLOCK_DIM``-th point and sums it into the log-likelihood, the lanes' sums reduced once; on the CPU one
thread per particle loops over the points (:mod:`warptan.kernels.likelihood`). The (N, M) residuals are stored
too.
Particle i belongs to filter ``b = i // n_per`` of a batch and reads that filter's measurement.
"""

import warp as wp

from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.likelihood import (
    CR_VALID,
    LIK_PAPER,
    LikParams,
    acc_add,
    acc_block_total,
    acc_finish,
    acc_init,
    acc_modes,
    acc_point,
    acc_set_modes,
    acc_store,
    cloud_row,
    gross_miss,
    mode_post,
    modes_block_total,
    modes_init,
    modes_vec,
    per_particle_kernels,
    row_dir,
    row_point,
)
from warptan.kernels.terrain import HeightGrid, grid_gradient, grid_height, grid_height_gradient, is_nan

wp.set_module_options({"enable_backward": False})


@wp.func
def sliding_jacobian(mat: wp.mat33, c: wp.vec3, gap: float, n_s: wp.vec3) -> wp.vec3:
    """``∂ĉ_z/∂dθ`` of the sliding prediction (design notes §6b), m/rad: with ``g = R e₃``, the map gradient
    ``(h_n, h_e)`` under the point and ``u = (g_n - h_n g_z, g_e - h_e g_z, 0)`` it is ``H = e₃ × ĉ - (Rᵀu) × c``;
    as ``u = g - g_z ∇F`` (``∇F = (h_n, h_e, 1)``) and ``ĉ - c = gap Rᵀe₃``, the same
    ``H = gap e₃ × Rᵀe₃ + g_z (n_s × c)`` with ``n_s = Rᵀ∇F`` (the map's normal in the sensor frame) and ``gap`` the
    point's height below the map's surface (m)."""
    return wp.vec3(-gap * mat[2, 1], gap * mat[2, 0], 0.0) + mat[2, 2] * wp.cross(n_s, c)


@wp.func
def sliding_var(p: LikParams, g_z: float, slope_dot: float) -> float:
    """σ² of one sliding residual (m²): range noise e along the ray ``u = R d`` moves the point by ``e u`` and the
    map height under it, so the residual ``c_z - ĉ_z = g_z × (vertical gap)`` moves by ``g_z (∇F · u) e``
    (``∇F = (h_n, h_e, 1)``, ``g_z = (R e₃)_z``); a vertical map error ``g_z`` times itself:
    ``σ_j = |g_z| sqrt(σ_range² (∇F · u)² + σ_map²)``, with ``|g_z| ≥ 0.2`` and ``|∇F · u| ≥ 0.25`` (a ray
    grazing the slope: the linear propagation no longer holds). A noiseless sensor (σ_range = 0) keeps the
    likelihood's own σ (its floor).

    Under map-error modes (``p.n_modes > 0``) the slope factor is 1 (``∇F · u`` of level ground under a vertical
    ray): the modes are the error field's patterns whitened by one σ (:meth:`warptan.sensing.likelihood.Likelihood.
    error_modes`), while a vertical map error moves this residual by ``g_z e`` whatever the slope, so a per-point
    ``σ_j`` whitens the field ``e_j / σ_j`` off the modes' span by the spread of ``∇F · u`` over the scan (about
    ±15 % on the 90 m rugged tile at 30° off nadir): with a 5 m error and σ = 0.5 m over a metre per point that no
    mode holds, the same in every scan that sees the ground, read as independent. Measured (S8 over a world whose
    only error is a 5 m / 1 km field on the map's own posts, ``world_refine = 1``, told it, 4 seeds, CPU): 4.0 m at
    3σ coverage north/east 94/20 % with the slope factor, 2.3 m at 99/66 % without (the range noise's own ±15 %
    spread is then left out: a small misstatement of the white part against a field 10 σ high)."""
    if p.sigma_range <= 0.0:
        return p.sigma * p.sigma
    geo = float(1.0)
    if p.n_modes == 0:
        geo = wp.max(wp.abs(slope_dot), 0.25)
    g = wp.max(wp.abs(g_z), 0.2)
    return g * g * (p.sigma_range * p.sigma_range * geo * geo + p.sigma_map * p.sigma_map)


def _sliding_loglik(tiled: bool, with_modes: bool):
    @wp.kernel
    def sliding_loglik_kernel(
        row0: int,
        n_per: int,
        grid: HeightGrid,
        surface: int,
        pos_n: wp.array(dtype=wp.vec3),
        quat_nb: wp.array(dtype=wp.vec4),
        cloud: wp.array2d(dtype=cloud_row),
        att_cov: wp.array(dtype=wp.mat33),
        params: LikParams,
        modes: wp.array(dtype=modes_vec),
        mode_mean: wp.array(dtype=modes_vec),
        mode_var: wp.array(dtype=modes_vec),
        residual_out: wp.array2d(dtype=wp.float32),
        err_out: wp.array(dtype=wp.float32),
        loglik_out: wp.array(dtype=wp.float32),
        nis_out: wp.array(dtype=wp.float32),
        n_valid_out: wp.array(dtype=wp.int32),
        lam_out: wp.array(dtype=wp.mat33),
        info_out: wp.array(dtype=wp.vec3),
        post_out: wp.array(dtype=modes_vec),
    ):
        """Particle ``t`` (one block, or one thread): residuals ``c_j,z - c^_ij,z`` (m) of the received points,
        error, log-likelihood (marginalised over the filter's attitude covariance ``att_cov[b]`` for the per-point
        forms), NIS, the attitude information Λ, b of the residuals and the map-error mode amplitudes for the next
        scan (:mod:`warptan.kernels.likelihood`)."""
        if wp.static(tiled):
            t, lane = wp.tid()
            stride = wp.block_dim()
        else:
            t = wp.tid()
            lane = 0
            stride = 1
        b = (row0 + t) // n_per
        mat = quat_to_mat_wxyz(quat_nb[t])
        p = pos_n[t]
        ones = wp.vec3(1.0, 1.0, 1.0)
        acc = acc_init()
        macc = modes_init()
        for j in range(lane, cloud.shape[1], stride):
            row = cloud[b, j]
            res = float(wp.nan)
            if row[CR_VALID] != 0.0:
                acc.n_recv = acc.n_recv + 1
                c = row_point(row)
                w = p + mat * c
                h, grad = grid_height_gradient(grid, surface, w[0], w[1])
                # ĉ = Rᵀ((w_n, w_e, -h) - p) = c + gap Rᵀe₃ with gap = -h - w_d: the residual c_z - ĉ_z
                gap = -h - w[2]
                res = -gap * mat[2, 2]
                if not is_nan(res):
                    nabla = wp.vec3(grad[0], grad[1], 1.0)
                    n_s = wp.transpose(mat) * nabla  # ∇F in the sensor frame: ∇F · (R d) = n_s · d
                    var = sliding_var(params, mat[2, 2], wp.dot(n_s, row_dir(row)))
                    jac = sliding_jacobian(mat, c, gap, n_s)
                    jac_pos = nabla * (-mat[2, 2])  # ∂ĉ_z/∂p = -g_z ∇F
                    miss = gross_miss(params, res, var, 1.0)
                    acc_point(acc, params, miss, res, var, 1.0, wp.nan, ones, jac, jac_pos)
                    if wp.static(with_modes):
                        if not miss:
                            acc_modes(macc, params, modes[j], res, var, jac, jac_pos)
            residual_out[t, j] = res
        if wp.static(tiled):
            acc = acc_block_total(acc)
            if wp.static(with_modes):
                macc = modes_block_total(macc)
        if lane == 0:
            if wp.static(with_modes):
                macc = acc_set_modes(macc, modes, cloud.shape[1], mode_mean[t], mode_var[b])
                post_out[t] = mode_post(macc, modes, cloud.shape[1])
            acc_store(t, acc, macc, params, att_cov[b], err_out, loglik_out, nis_out, n_valid_out, lam_out,
                      info_out)

    return sliding_loglik_kernel


sliding_loglik_kernels = per_particle_kernels(_sliding_loglik)
"""The fused sliding model: ``[(True, modes)]`` tiled (``wp.launch_tiled``, CUDA), ``[(False, modes)]`` one thread
per particle; ``modes``: with the map-error modes (a stated map error)."""


KERNEL_POINT_SCALE = wp.constant(1.7320508)  # sqrt(n + κ) of the horizontal kernel's unscented points (n = 2, κ = 1)


@wp.func
def kernel_height(grid: HeightGrid, surface: int, p: wp.vec3, chol: wp.mat33):
    """(mean, variance) in m, m² of the map's height over a particle's kernel: the Gaussian about ``p`` whose
    horizontal covariance has the lower Cholesky factor ``chol[:2, :2]`` (the regularisation kernel the particle stands
    for and resampling draws from), from the unscented transform's five points (``p``, weight 1/3; ``p ± sqrt(3) c_j``
    for the factor's columns c_j, 1/6 each; heights relative to ``h(p)``, so float32 does not cancel). Points off the
    map are left out (their weight to the others); a zero kernel or a centre off the map gives ``(h(p), 0)``."""
    h0 = grid_height(grid, surface, p[0], p[1])
    c0 = wp.vec2(chol[0, 0], chol[1, 0])
    c1 = wp.vec2(0.0, chol[1, 1])
    if is_nan(h0) or (c0[0] == 0.0 and c0[1] == 0.0 and c1[1] == 0.0):
        return h0, float(0.0)
    sw = 1.0 / 3.0
    s1 = float(0.0)
    s2 = float(0.0)
    for j in range(4):
        c = c0
        if j >= 2:
            c = c1
        sign = 1.0
        if j % 2 == 1:
            sign = -1.0
        d = (sign * KERNEL_POINT_SCALE) * c
        dh = grid_height(grid, surface, p[0] + d[0], p[1] + d[1]) - h0
        if not is_nan(dh):
            sw += 1.0 / 6.0
            s1 += dh / 6.0
            s2 += dh * dh / 6.0
    mean = s1 / sw
    return h0 + mean, wp.max(s2 / sw - mean * mean, 0.0)


@wp.kernel
def altimeter_loglik_kernel(
    n_per: int,
    grid: HeightGrid,
    surface: int,
    use_baro: int,
    pos_n: wp.array(dtype=wp.vec3),
    reading: wp.array(dtype=wp.vec4),
    params: LikParams,
    modes: wp.array(dtype=modes_vec),
    mode_mean: wp.array(dtype=modes_vec),
    mode_var: wp.array(dtype=modes_vec),
    kernel_chol: wp.array(dtype=wp.mat33),
    residual_out: wp.array2d(dtype=wp.float32),
    err_out: wp.array(dtype=wp.float32),
    loglik_out: wp.array(dtype=wp.float32),
    nis_out: wp.array(dtype=wp.float32),
    n_valid_out: wp.array(dtype=wp.int32),
    lam_out: wp.array(dtype=wp.mat33),
    info_out: wp.array(dtype=wp.vec3),
    post_out: wp.array(dtype=modes_vec),
    info_pos_out: wp.array(dtype=wp.vec3),
):
    """One thread per particle; ``reading[b] = [range a, h_baro, valid, 1/σ_baro²]``: residual
    ``a - (h_baro - h̄_i)`` in m (without a barometer, ``use_baro == 0``, the particle's own altitude ``-p_i,z``
    replaces ``h_baro``) of standard deviation ``sqrt(σ² + v_i)``: ``h̄_i``, ``v_i`` the mean and variance of the map's
    height over the particle's regularisation kernel ``kernel_chol[b]`` (:func:`kernel_height`; ``h(p_i)`` and 0 for a
    zero kernel), i.e. the Gaussian approximation of ``∫ N(a; h_baro - h(x), σ²) K(x - p_i) dx``: a particle stands for
    its kernel, and without it the one particle that happens to lie on the right contour wins over the one nearest the
    truth, a few metres off and so a few σ off. With a barometer it is also scored as a measurement of the particle's
    altitude: ``loglik_i += -0.5 (h_baro + p_i,z)² / σ_baro²``. ``info_pos_out``: ``g gᵀ / σ²`` (nn, ee, ne; m⁻²)
    with g = ∇h at the particle (zero for the paper's scalar error or an invalid residual)."""
    i = wp.tid()
    b = i // n_per
    r = reading[b]
    p = pos_n[i]
    acc = acc_init()
    macc = modes_init()
    res = float(wp.nan)
    info_pos = wp.vec3()
    if r[2] != 0.0:
        acc.n_recv = 1
        alt = r[1]
        if use_baro == 0:
            alt = -p[2]
        kernel = kernel_chol[b]
        if params.lik == LIK_PAPER:  # the paper's scalar error scores the particle itself
            kernel = wp.mat33()
        h, var = kernel_height(grid, surface, p, kernel)
        res = r[0] - (alt - h)
        if not is_nan(res):
            res_var = params.sigma * params.sigma
            if var > 0.0:
                res_var = res_var + var
            if params.lik != LIK_PAPER:
                g = grid_gradient(grid, surface, p[0], p[1])
                iv = 1.0 / res_var
                info_pos = wp.vec3(g[0] * g[0] * iv, g[1] * g[1] * iv, g[0] * g[1] * iv)
            acc_add(acc, params, res, res_var, wp.vec3(1.0, 1.0, 1.0), wp.vec3(), wp.vec3())
            if params.n_modes > 0:
                acc_modes(macc, params, modes[0], res, res_var, wp.vec3(), wp.vec3())
    if params.n_modes > 0:
        macc = acc_set_modes(macc, modes, 1, mode_mean[i], mode_var[b])
        post_out[i] = mode_post(macc, modes, 1)
    residual_out[i, 0] = res
    err, ll, nis = acc_finish(acc, macc, params, wp.mat33())
    if use_baro != 0 and r[2] != 0.0:
        d = r[1] + p[2]
        ll = ll - 0.5 * d * d * r[3]
    err_out[i] = err
    loglik_out[i] = ll
    nis_out[i] = nis
    n_valid_out[i] = acc.n_ok
    lam_out[i] = wp.mat33()  # a nadir range does not see the attitude to first order
    info_out[i] = wp.vec3()
    info_pos_out[i] = info_pos
