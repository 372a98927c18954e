"""Height-sampling measurement models: the sliding grid (paper eq. 14, 16) and the altimeter (eq. 8, 17).

No ray is cast. Sliding: each received point ``c_j`` (sensor frame) is placed with the hypothetical pose,
``w_ij = p_i + R_i c_j``; the map is read under it, ``w^_ij = (w_x, w_y, -h(w_x, w_y))``; the predicted
point is ``c^_ij = R_i^T (w^_ij - p_i)`` and the residual is ``c_j,z - c^_ij,z`` (m). Altimeter: the
predicted range is ``a^_i = h_baro - h(p_i,x, p_i,y)`` and the residual ``a - a^_i`` (m).
A point or particle off the map, on nodata, or with a NaN input gives a NaN residual (excluded later).
"""

import warp as wp

from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.terrain import HeightGrid, grid_height

wp.set_module_options({"enable_backward": False})


@wp.kernel
def sliding_residual_kernel(
    grid: HeightGrid,
    surface: int,
    pos_n: wp.array(dtype=wp.vec3),
    quat_nb: wp.array(dtype=wp.vec4),
    points_s: wp.array(dtype=wp.vec3),
    residual_out: wp.array2d(dtype=wp.float32),
):
    """One thread per (particle i, point j): sensor-frame z residual ``c_j,z - c^_ij,z`` in m."""
    i, j = wp.tid()
    c = points_s[j]
    if wp.isnan(c[0] + c[1] + c[2]):
        residual_out[i, j] = wp.nan
        return
    mat = quat_to_mat_wxyz(quat_nb[i])
    p = pos_n[i]
    w = p + mat * c
    h = grid_height(grid, surface, w[0], w[1])
    c_hat = wp.transpose(mat) * (wp.vec3(w[0], w[1], -h) - p)
    residual_out[i, j] = c[2] - c_hat[2]


@wp.kernel
def altimeter_residual_kernel(
    grid: HeightGrid,
    surface: int,
    use_baro: int,
    pos_n: wp.array(dtype=wp.vec3),
    range_m: float,
    baro_alt_m: float,
    residual_out: wp.array2d(dtype=wp.float32),
):
    """One thread per particle: ``a - (h_baro - h(p_i,x, p_i,y))`` in m, stored as the (N, 1) residual;
    without a barometer (``use_baro == 0``) the particle's own altitude ``-p_i,z`` replaces ``h_baro``."""
    i = wp.tid()
    p = pos_n[i]
    alt = baro_alt_m
    if use_baro == 0:
        alt = -p[2]
    residual_out[i, 0] = range_m - (alt - grid_height(grid, surface, p[0], p[1]))


@wp.kernel
def add_baro_loglik_kernel(
    pos_n: wp.array(dtype=wp.vec3),
    baro_alt_m: float,
    inv_var: float,
    loglik: wp.array(dtype=wp.float32),
):
    """One thread per particle: ``loglik_i += -0.5 (h_baro - (-p_i,z))² / σ_baro²`` (the barometer as a
    measurement of each particle's altitude)."""
    i = wp.tid()
    r = baro_alt_m + pos_n[i][2]
    loglik[i] = loglik[i] - 0.5 * r * r * inv_var
