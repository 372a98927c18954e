"""The Fisher information a scan carries about the aircraft's position, at every cell of a map
(:func:`warptan.terrain.information.information_map`).

At cell c the scan reads the map at the footprint points ``c + o_p`` (``offsets``: the nominal footprint, the same for
every cell); point p's residual moves with the position error ``δ = (δn, δe, δd)`` as ``H_p δ`` with
``H_p = (∂h/∂n, ∂h/∂e, v)`` at the point (``v = 1``: the altitude is unknown and read by the scan, a point cloud;
``v = 0``: a barometer fixes it, the altimeter). With residual covariance ``R = σ_w² I + Σ_k λ_k u_k u_kᵀ`` (white
noise plus the map's correlated error as modes over the footprint) the information is ``J = Hᵀ R⁻¹ H = (Σ_p H_p H_pᵀ
− Σ_k c_k q_k q_kᵀ) / σ_w²`` with ``q_k = Σ_p u_pk H_p`` and ``c_k = λ_k / (σ_w² + λ_k)`` (Woodbury): one pass over
the footprint per cell, in float64. A cell whose footprint reads nodata or leaves the map gets NaN.
"""

import warp as wp

from warptan.kernels.terrain import HeightGrid, grid_height_gradient, is_nan

wp.set_module_options({"enable_backward": False})

MAX_INFO_MODES = 32
"""Most map-error modes the kernel carries (the host folds the rest into the white variance)."""


@wp.kernel
def scan_information_kernel(
    grid: HeightGrid,
    surface: int,
    stride: int,
    offsets: wp.array(dtype=wp.vec2),
    modes: wp.array2d(dtype=wp.float32),
    weights: wp.array(dtype=wp.float64),
    n_modes: int,
    vertical: float,
    inv_var: wp.float64,
    info_out: wp.array2d(dtype=wp.mat33d),
):
    """One thread per output cell (every ``stride``-th post): ``info_out[i, j]`` = J (3×3, m⁻²) of the scan over
    post ``(i · stride, j · stride)``."""
    i, j = wp.tid()
    north = grid.n0 + float(i * stride) * grid.dn
    east = grid.e0 + float(j * stride) * grid.de
    s = wp.mat33d()
    q = wp.matrix(shape=(MAX_INFO_MODES, 3), dtype=wp.float64)
    valid = int(1)
    for p in range(offsets.shape[0]):
        o = offsets[p]
        h, g = grid_height_gradient(grid, surface, north + o[0], east + o[1])
        if is_nan(h) or is_nan(g[0]) or is_nan(g[1]):
            valid = 0
        else:
            hv = wp.vec3d(wp.float64(g[0]), wp.float64(g[1]), wp.float64(vertical))
            s += wp.outer(hv, hv)
            for k in range(n_modes):
                u = wp.float64(modes[p, k])
                q[k, 0] = q[k, 0] + u * hv[0]
                q[k, 1] = q[k, 1] + u * hv[1]
                q[k, 2] = q[k, 2] + u * hv[2]
    for k in range(n_modes):
        qk = wp.vec3d(q[k, 0], q[k, 1], q[k, 2])
        s -= weights[k] * wp.outer(qk, qk)
    if valid == 0:
        nan = wp.float64(wp.nan)
        s = wp.mat33d(nan, nan, nan, nan, nan, nan, nan, nan, nan)
    info_out[i, j] = s * inv_var


@wp.func
def info_at(field: wp.array2d(dtype=wp.mat33d), u: float, v: float) -> wp.mat33d:
    """Bilinear interpolation of a field of 3×3 information matrices at fractional row ``u``, column ``v``; NaN off
    the field."""
    rows = field.shape[0]
    cols = field.shape[1]
    if u >= 0.0 and u <= float(rows - 1) and v >= 0.0 and v <= float(cols - 1) and rows > 1 and cols > 1:
        i = wp.min(int(u), rows - 2)
        j = wp.min(int(v), cols - 2)
        fu = wp.float64(u - float(i))
        fv = wp.float64(v - float(j))
        one = wp.float64(1.0)
        return (one - fu) * ((one - fv) * field[i, j] + fv * field[i, j + 1]) + fu * (
            (one - fv) * field[i + 1, j] + fv * field[i + 1, j + 1])
    nan = wp.float64(wp.nan)
    return wp.mat33d(nan, nan, nan, nan, nan, nan, nan, nan, nan)


@wp.kernel
def leg_information_kernel(
    field: wp.array2d(dtype=wp.mat33d),
    cell_n: float,
    cell_e: float,
    shifts: wp.array(dtype=wp.vec2),
    info_out: wp.array2d(dtype=wp.mat33d),
):
    """One thread per cell: the information of the leg's scans through it, ``Σ_s field(cell + shift_s)`` (the field
    read bilinearly; ``cell_n``, ``cell_e``: the field's cell size, m)."""
    i, j = wp.tid()
    s = wp.mat33d()
    for k in range(shifts.shape[0]):
        d = shifts[k]
        s += info_at(field, float(i) + d[0] / cell_n, float(j) + d[1] / cell_e)
    info_out[i, j] = s
