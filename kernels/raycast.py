"""Ray casting against the DEM (paper §III, eq. 6 and 15; design notes §5): mesh BVH, heightfield DDA, bisection.

All three backends see the same surface: the triangulated grid of :mod:`warptan.kernels.terrain` (two
triangles per cell, diagonal (i, j)-(i+1, j+1)). A ray is ``o + t d`` in NED metres; ``d`` is normalised
here, so ``t`` is a range in metres. Every backend returns NaN (no hit), never a made-up range, when

* the origin is off the grid, or below the terrain surface (a particle inside the ground);
* the ray leaves the grid before hitting, or points away from the terrain (up into the sky);
* the ray meets nodata: for ``dda`` and ``bisection`` any cell with a nodata post crossed inside the
  terrain's height band; for ``mesh`` (holes have no triangles) a ray that falls through a hole and
  then meets the underside of the surface or nothing.

``dda``: the exact traversal of the grid cells under the ray (2-D DDA, Amanatides & Woo), the ray first
clipped to the terrain's min–max height band, cells whose highest post is below the ray skipped, and an
exact intersection with the two triangles of every other cell (front faces only). The CPU's per-particle form of the
filter's ray casts (:data:`raycast_residual_rows_kernel`) starts a ray lower, where it comes down to the highest post
within its reach (:func:`local_band_entry`): the same cells are tested, the same ranges found; and its surface normal
is the slopes of the triangle the DDA hit (:func:`cell_hit`), not the map read again at the hit point. The CPU's
filter runs that kernel with its rays cast in SIMD lanes (:mod:`warptan.kernels.simd_ray`, the same ranges and slopes).
``bisection``: the paper's CPU variant: march in horizontal steps of ``step_m`` (≤ half a post by
default) until the first sample on or below the surface, then ``n_bisect`` halvings of the last step.
It finds the first surface unless a feature is thinner than a step.
"""

import warp as wp

from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.likelihood import CR_RANGE, CR_VALID, cloud_row, row_dir
from warptan.kernels.terrain import BLOCK_CELLS, HeightGrid, grid_gradient, grid_surface, is_finite, is_nan

wp.set_module_options({"enable_backward": False})

BACKEND_MESH = wp.constant(0)
BACKEND_DDA = wp.constant(1)
BACKEND_BISECTION = wp.constant(2)

BIG = wp.constant(1.0e30)
EDGE_EPS = wp.constant(1.0e-5)
BAND_PAD = wp.constant(0.05)
RESIDUAL_MAX_REGISTERS = 64
"""Registers a thread of :data:`raycast_residual_kernel` may hold on CUDA (``__maxnreg__``): the compiler gave it 125,
which left a quarter of an H100's warps resident; at 64 half of them are. S7's model (the residual kernel and the
per-particle reduction, N = 500, M = 400) took 39.0 µs against 43.1 µs (96 registers: 42.8 µs), the same bits
(``scripts/bench_update_pieces.py``, ``scripts/step_digest.py``)."""


@wp.func
def no_hit() -> wp.vec3:
    """What :func:`dda_march` gives for a ray that meets no surface: range NaN, slopes 0."""
    return wp.vec3(wp.nan, 0.0, 0.0)


@wp.func
def origin_blocked(grid: HeightGrid, o: wp.vec3) -> bool:
    """True when a ray from ``o`` cannot be cast: off the grid, or below the known terrain surface."""
    rows = grid.heights.shape[0]
    cols = grid.heights.shape[1]
    u = (o[0] - grid.n0) / grid.dn
    v = (o[1] - grid.e0) / grid.de
    if not (u >= 0.0 and u <= float(rows - 1) and v >= 0.0 and v <= float(cols - 1) and o[2] == o[2]):
        return True
    h = grid_surface(grid, o[0], o[1])
    if not is_nan(h):
        if o[2] > -h:
            return True
    return False


@wp.func
def band_interval(grid: HeightGrid, o: wp.vec3, d: wp.vec3) -> wp.vec2:
    """``[t_in, t_out]`` (t_in ≥ 0) where the ray is inside the terrain's height band; t_in > t_out: never."""
    # Widened by BAND_PAD so that rounding cannot drop a hit on a flat band (h_min == h_max).
    z_top = -grid.h_max - BAND_PAD
    z_bot = -grid.h_min + BAND_PAD
    t_in = float(0.0)
    t_out = float(BIG)
    if d[2] > 0.0:
        t_in = wp.max(0.0, (z_top - o[2]) / d[2])
        t_out = (z_bot - o[2]) / d[2]
    elif d[2] < 0.0:
        t_in = wp.max(0.0, (z_bot - o[2]) / d[2])
        t_out = (z_top - o[2]) / d[2]
    elif o[2] < z_top or o[2] > z_bot:
        t_out = float(-1.0)
    return wp.vec2(t_in, t_out)


@wp.func
def grid_exit(grid: HeightGrid, o: wp.vec3, d: wp.vec3) -> float:
    """Largest ``t`` at which the ray (origin on the grid) is still over the grid, less 1 mm."""
    rows = grid.heights.shape[0]
    cols = grid.heights.shape[1]
    n_max = grid.n0 + float(rows - 1) * grid.dn
    e_max = grid.e0 + float(cols - 1) * grid.de
    t = float(BIG)
    if d[0] > 0.0:
        t = wp.min(t, (n_max - o[0]) / d[0])
    elif d[0] < 0.0:
        t = wp.min(t, (grid.n0 - o[0]) / d[0])
    if d[1] > 0.0:
        t = wp.min(t, (e_max - o[1]) / d[1])
    elif d[1] < 0.0:
        t = wp.min(t, (grid.e0 - o[1]) / d[1])
    return t - 1.0e-3


@wp.func
def cell_hit(grid: HeightGrid, i: int, j: int, o: wp.vec3, d: wp.vec3) -> wp.vec3:
    """``(t, ∂h/∂n, ∂h/∂e)``: the smallest ``t ≥ 0`` where the ray enters one of the two triangles of cell (i, j) from
    above and that triangle's slopes (the surface gradient there, as :func:`~warptan.kernels.terrain.grid_gradient`
    computes it); ``t`` = -1 if none."""
    h00 = grid.heights[i, j]
    h10 = grid.heights[i + 1, j]
    h01 = grid.heights[i, j + 1]
    h11 = grid.heights[i + 1, j + 1]
    a = o[0] - (grid.n0 + float(i) * grid.dn)
    b = o[1] - (grid.e0 + float(j) * grid.de)
    best = wp.vec3(-1.0, 0.0, 0.0)
    # Triangle A, U >= V: h = h00 + U (h10 - h00) + V (h11 - h10); f(t) = z(t) + h(t), above the surface f < 0.
    su = (h10 - h00) * grid.inv_dn
    sv = (h11 - h10) * grid.inv_de
    f1 = d[2] + d[0] * su + d[1] * sv
    if f1 > 0.0:
        t = -(o[2] + h00 + a * su + b * sv) / f1
        if t >= 0.0:
            uu = (a + t * d[0]) * grid.inv_dn
            vv = (b + t * d[1]) * grid.inv_de
            if vv >= -EDGE_EPS and uu <= 1.0 + EDGE_EPS and uu >= vv - EDGE_EPS:
                best = wp.vec3(t, su, sv)
    # Triangle B, V >= U: h = h00 + V (h01 - h00) + U (h11 - h01).
    su = (h11 - h01) * grid.inv_dn
    sv = (h01 - h00) * grid.inv_de
    f1 = d[2] + d[0] * su + d[1] * sv
    if f1 > 0.0:
        t = -(o[2] + h00 + a * su + b * sv) / f1
        if t >= 0.0 and (best[0] < 0.0 or t < best[0]):
            uu = (a + t * d[0]) * grid.inv_dn
            vv = (b + t * d[1]) * grid.inv_de
            if uu >= -EDGE_EPS and vv <= 1.0 + EDGE_EPS and vv >= uu - EDGE_EPS:
                best = wp.vec3(t, su, sv)
    return best


@wp.func
def local_band_entry(grid: HeightGrid, o: wp.vec3, d: wp.vec3, t_in: float, t_end: float) -> float:
    """Where a descending ray (unit ``d``, origin ``o`` on the grid) comes down to the highest surface within its
    reach, no earlier than ``t_in``: when its horizontal reach to the band's bottom (``t_end``) is at most
    ``BLOCK_CELLS`` cells, every cell it crosses lies in the origin's block or a neighbour, whose
    :attr:`HeightGrid.block_top` bounds their posts; above it :func:`cast_dda` would only skip cells (their highest
    post below the ray). The global band's top lies hundreds of metres above a scan's ground on a rugged tile (S7: 983
    m against ~500 m within 2 km of the track). Else (farther reach, a level ray, nodata within reach) ``t_in``."""
    if d[2] <= 0.0:
        return t_in
    reach = float(BLOCK_CELLS) * wp.min(grid.dn, grid.de)
    if (d[0] * d[0] + d[1] * d[1]) * t_end * t_end > reach * reach:
        return t_in
    i = wp.min(int((o[0] - grid.n0) / grid.dn), grid.heights.shape[0] - 2)
    j = wp.min(int((o[1] - grid.e0) / grid.de), grid.heights.shape[1] - 2)
    top = grid.block_top[i // BLOCK_CELLS, j // BLOCK_CELLS]
    if top > 1.0e37:
        return t_in
    return wp.max(t_in, (-top - BAND_PAD - o[2]) / d[2])


@wp.func
def dda_march(grid: HeightGrid, o: wp.vec3, d: wp.vec3, t_start: float, t_end: float) -> wp.vec3:
    """The 2-D DDA of :func:`cast_dda` over the ray's ``[t_start, t_end]`` (within the terrain's height band): the
    hit's :func:`cell_hit` ``(t, ∂h/∂n, ∂h/∂e)``, ``t`` NaN where none (:func:`no_hit`)."""
    t = t_start
    rows = grid.heights.shape[0]
    cols = grid.heights.shape[1]
    u = (o[0] + t * d[0] - grid.n0) / grid.dn
    v = (o[1] + t * d[1] - grid.e0) / grid.de
    if not (u >= 0.0 and u <= float(rows - 1) and v >= 0.0 and v <= float(cols - 1)):
        return no_hit()  # the ray leaves the map before it comes down to the terrain
    i = wp.min(int(wp.floor(u)), rows - 2)
    j = wp.min(int(wp.floor(v)), cols - 2)
    du = d[0] * grid.inv_dn
    dv = d[1] * grid.inv_de
    step_i = int(1)
    step_j = int(1)
    t_next_u = float(BIG)
    t_delta_u = float(BIG)
    t_next_v = float(BIG)
    t_delta_v = float(BIG)
    if du > 0.0:
        t_next_u = t + (float(i + 1) - u) / du
        t_delta_u = 1.0 / du
    elif du < 0.0:
        step_i = int(-1)
        t_next_u = t + (float(i) - u) / du
        t_delta_u = -1.0 / du
    if dv > 0.0:
        t_next_v = t + (float(j + 1) - v) / dv
        t_delta_v = 1.0 / dv
    elif dv < 0.0:
        step_j = int(-1)
        t_next_v = t + (float(j) - v) / dv
        t_delta_v = -1.0 / dv
    for _it in range(rows + cols + 4):
        t_cell_end = wp.min(wp.min(t_next_u, t_next_v), t_end)
        # Lowest point of the ray over this cell (largest z): above the cell's highest post, skip the cell.
        z_low = wp.max(o[2] + t * d[2], o[2] + t_cell_end * d[2])
        cmax = grid.cell_max[i, j]
        if -z_low <= cmax + BAND_PAD:
            if cmax > 1.0e37:
                return no_hit()  # nodata cell inside the height band
            th = cell_hit(grid, i, j, o, d)
            if th[0] >= 0.0:
                return th
        if t_cell_end >= t_end:
            return no_hit()
        if t_next_u < t_next_v:
            i += step_i
            t = t_next_u
            t_next_u += t_delta_u
        else:
            j += step_j
            t = t_next_v
            t_next_v += t_delta_v
        if i < 0 or i > rows - 2 or j < 0 or j > cols - 2:
            return no_hit()  # left the map
    return no_hit()


@wp.func
def cast_dda(grid: HeightGrid, o: wp.vec3, d: wp.vec3) -> float:
    """Range (m) of the first surface hit along unit ``d`` by 2-D DDA over the cells; NaN = no hit."""
    if origin_blocked(grid, o):
        return wp.nan
    band = band_interval(grid, o, d)
    if band[0] > band[1]:
        return wp.nan
    return dda_march(grid, o, d, band[0], band[1])[0]


@wp.func
def cast_bisection(grid: HeightGrid, o: wp.vec3, d: wp.vec3, step_m: float, n_bisect: int) -> float:
    """Range (m) by marching ``step_m`` horizontally to the first sample on/below the surface, then bisection."""
    if origin_blocked(grid, o):
        return wp.nan
    band = band_interval(grid, o, d)
    t_prev = band[0]
    t_end = wp.min(band[1], grid_exit(grid, o, d))
    if t_prev > t_end:
        return wp.nan
    horiz = wp.sqrt(d[0] * d[0] + d[1] * d[1])
    t_step = t_end - t_prev
    if horiz * t_step > step_m:
        t_step = step_m / horiz
    t_step = wp.max(t_step, 1.0e-3)  # a flat band (h_min == h_max) crossed vertically
    n_steps = int(wp.ceil((t_end - t_prev) / t_step)) + 1
    for _k in range(n_steps):
        t_cur = wp.min(t_prev + t_step, t_end)
        p = o + t_cur * d
        h = grid_surface(grid, p[0], p[1])
        if is_nan(h):
            return wp.nan  # left the map or met nodata
        if p[2] + h >= 0.0:
            lo = t_prev
            hi = t_cur
            for _b in range(n_bisect):
                mid = 0.5 * (lo + hi)
                q = o + mid * d
                hq = grid_surface(grid, q[0], q[1])
                if is_nan(hq) or q[2] + hq >= 0.0:
                    hi = mid
                else:
                    lo = mid
            return 0.5 * (lo + hi)
        if t_cur >= t_end:
            return wp.nan  # out of the height band (sky) or off the map
        t_prev = t_cur
    return wp.nan


@wp.func
def cast_mesh(grid: HeightGrid, mesh: wp.uint64, o: wp.vec3, d: wp.vec3) -> float:
    """Range (m) of the first front-face hit on the triangle mesh (``wp.mesh_query_ray``); NaN = no hit."""
    if origin_blocked(grid, o):
        return wp.nan
    band = band_interval(grid, o, d)
    if band[0] > band[1]:
        return wp.nan
    q = wp.mesh_query_ray(mesh, o, d, band[1] + 1.0)
    if q.result and q.sign > 0.0:
        return q.t
    return wp.nan


@wp.func
def cast_ray(
    grid: HeightGrid, mesh: wp.uint64, backend: int, o: wp.vec3, d_raw: wp.vec3, step_m: float, n_bisect: int
) -> float:
    """Dispatch one ray to a backend (``BACKEND_*``); ``d_raw`` is normalised first."""
    d = wp.normalize(d_raw)
    if backend == BACKEND_MESH:
        return cast_mesh(grid, mesh, o, d)
    if backend == BACKEND_DDA:
        return cast_dda(grid, o, d)
    return cast_bisection(grid, o, d, step_m, n_bisect)


@wp.kernel
def raycast_kernel(
    grid: HeightGrid,
    mesh: wp.uint64,
    backend: int,
    step_m: float,
    n_bisect: int,
    origins_n: wp.array(dtype=wp.vec3),
    dirs_n: wp.array(dtype=wp.vec3),
    range_out: wp.array(dtype=wp.float32),
):
    """One thread per ray: range in m along the normalised direction, NaN = no hit."""
    k = wp.tid()
    range_out[k] = cast_ray(grid, mesh, backend, origins_n[k], dirs_n[k], step_m, n_bisect)


@wp.kernel
def raycast_pattern_kernel(
    grid: HeightGrid,
    mesh: wp.uint64,
    backend: int,
    step_m: float,
    n_bisect: int,
    pos_n: wp.array(dtype=wp.vec3),
    quat_nb: wp.array(dtype=wp.vec4),
    dirs_s: wp.array(dtype=wp.vec3),
    range_out: wp.array2d(dtype=wp.float32),
):
    """One thread per (pose i, pattern ray j): cast ``R(q_i) d_j`` from ``p_i``."""
    i, j = wp.tid()
    d = quat_to_mat_wxyz(quat_nb[i]) * dirs_s[j]
    range_out[i, j] = cast_ray(grid, mesh, backend, pos_n[i], d, step_m, n_bisect)


@wp.kernel(cuda_max_registers=RESIDUAL_MAX_REGISTERS)
def raycast_residual_kernel(
    grid: HeightGrid,
    mesh: wp.uint64,
    backend: int,
    step_m: float,
    n_bisect: int,
    row0: int,
    n_per: int,
    pos_n: wp.array(dtype=wp.vec3),
    quat_nb: wp.array(dtype=wp.vec4),
    cloud: wp.array2d(dtype=cloud_row),
    residual_out: wp.array2d(dtype=wp.float32),
    normal_out: wp.array2d(dtype=wp.vec3),
    want_vertical: int,
    vertical_out: wp.array2d(dtype=wp.float32),
):
    """One thread per (particle i, point j): range residual ``r_j - t_ij`` (m); NaN where either is invalid.
    Particle ``row0 + i`` belongs to filter ``b = (row0 + i) // n_per`` and casts that filter's pattern.

    With ``c_j = r_j d_j`` and ``c^_ij = t_ij d_j`` the point residual is ``(r_j - t_ij) d_j`` (eq. 15).
    Also what the range's derivatives need: with the surface ``F = z + h(n, e) = 0``, ``∇F = (h_n, h_e, 1)`` at the
    hit and ``u = R d``, the scaled normal ``s = ∇F / (∇F · u)`` (zero at a grazing hit), from which
    :func:`warptan.kernels.likelihood.ray_jacobians` forms ``∂t/∂dθ = t (Rᵀs) × d`` (design notes §6b) and
    ``∂t/∂p = -s``.
    With ``want_vertical`` (the likelihood is told its map is not the world: :func:`warptan.kernels.likelihood.
    map_not_world`) also the received point's height above the map's surface, ``-q_z - h(q_n, q_e)`` with ``q = p +
    r_j d`` (m; NaN where the point is invalid or off the map): what a ray that met another surface still says
    (:func:`warptan.kernels.likelihood.acc_gated`); otherwise ``vertical_out`` is not written (nothing reads it).
    """
    i, j = wp.tid()
    row = cloud[(row0 + i) // n_per, j]
    normal_out[i, j] = wp.vec3()
    if row[CR_VALID] == 0.0:
        residual_out[i, j] = wp.nan
        if want_vertical != 0:
            vertical_out[i, j] = wp.nan
        return
    mat = quat_to_mat_wxyz(quat_nb[i])
    d_s = row_dir(row)
    d = mat * d_s
    p = pos_n[i]
    t = cast_ray(grid, mesh, backend, p, d, step_m, n_bisect)
    residual_out[i, j] = row[CR_RANGE] - t
    if want_vertical != 0:
        q = p + row[CR_RANGE] * d
        vertical_out[i, j] = -q[2] - grid_surface(grid, q[0], q[1])
    if not is_nan(t):
        hit = p + t * d
        grad = grid_gradient(grid, 1, hit[0], hit[1])
        nrm = wp.vec3(grad[0], grad[1], 1.0)
        den = wp.dot(nrm, d)
        if is_finite(den) and wp.abs(den) > 1.0e-3:
            normal_out[i, j] = nrm / den


@wp.func
def cast_unblocked_local(
    grid: HeightGrid, mesh: wp.uint64, backend: int, o: wp.vec3, d_raw: wp.vec3, step_m: float, n_bisect: int
) -> wp.vec3:
    """:func:`cast_ray` from an origin that has passed :func:`origin_blocked` (a particle's rays share the check), a
    DDA ray from its local band (:func:`local_band_entry`): the same range, as ``(t, ∂h/∂n, ∂h/∂e)`` with the slopes
    of the triangle the DDA hit (:func:`dda_march`; the other backends give 0: their caller reads the map)."""
    d = wp.normalize(d_raw)
    if backend == BACKEND_DDA:
        band = band_interval(grid, o, d)
        if band[0] > band[1]:
            return no_hit()
        return dda_march(grid, o, d, local_band_entry(grid, o, d, band[0], band[1]), band[1])
    if backend == BACKEND_MESH:
        return wp.vec3(cast_mesh(grid, mesh, o, d), 0.0, 0.0)
    return wp.vec3(cast_bisection(grid, o, d, step_m, n_bisect), 0.0, 0.0)


@wp.func
def point_not_received(i: int, j: int, want_vertical: int, residual_out: wp.array2d(dtype=wp.float32),
                       normal_out: wp.array2d(dtype=wp.vec3), vertical_out: wp.array2d(dtype=wp.float32)):
    """Point j of particle i, not received: residual (and height above the map) NaN, normal zero."""
    normal_out[i, j] = wp.vec3()
    residual_out[i, j] = wp.nan
    if want_vertical != 0:
        vertical_out[i, j] = wp.nan


@wp.func
def point_outputs(grid: HeightGrid, p: wp.vec3, d: wp.vec3, row: cloud_row, t: float, slopes: wp.vec2,
                  want_vertical: int, i: int, j: int, residual_out: wp.array2d(dtype=wp.float32),
                  normal_out: wp.array2d(dtype=wp.vec3), vertical_out: wp.array2d(dtype=wp.float32)):
    """Point j of particle i (origin ``p``, ray ``d = R d_s``) from its cast: range ``t`` (NaN: no hit) and the
    surface's slopes at the hit: the residual, with ``want_vertical`` the received point's height above the map, and
    the scaled normal (zero without a hit or at a grazing one); :data:`raycast_residual_kernel`'s outputs."""
    residual_out[i, j] = row[CR_RANGE] - t
    if want_vertical != 0:
        q = p + row[CR_RANGE] * d
        vertical_out[i, j] = -q[2] - grid_surface(grid, q[0], q[1])
    normal = wp.vec3()
    if not is_nan(t):
        nrm = wp.vec3(slopes[0], slopes[1], 1.0)
        den = wp.dot(nrm, d)
        if is_finite(den) and wp.abs(den) > 1.0e-3:
            normal = nrm / den
    normal_out[i, j] = normal


@wp.kernel
def raycast_residual_rows_kernel(
    grid: HeightGrid,
    mesh: wp.uint64,
    backend: int,
    step_m: float,
    n_bisect: int,
    row0: int,
    n_per: int,
    pos_n: wp.array(dtype=wp.vec3),
    quat_nb: wp.array(dtype=wp.vec4),
    cloud: wp.array2d(dtype=cloud_row),
    residual_out: wp.array2d(dtype=wp.float32),
    normal_out: wp.array2d(dtype=wp.vec3),
    want_vertical: int,
    vertical_out: wp.array2d(dtype=wp.float32),
):
    """:data:`raycast_residual_kernel` as one thread per particle i looping over its points, the CPU's form: the
    particle's rotation and origin check made once, not once per ray, and DDA rays cast from their local band
    (:func:`cast_unblocked_local`), and a DDA hit's normal from the slopes of the triangle it hit instead of the map
    read again at the hit point (:func:`~warptan.kernels.terrain.grid_gradient`: the same slopes, but for a hit within
    ``EDGE_EPS`` of a triangle's edge, which that read may place in the neighbouring triangle). The same ranges and
    bits otherwise on the CPU (S7, N = 500, 10 × 10 rays, one CPU thread: 5.9 → 4.4 ms; the hit's slopes 4.62 → 3.97
    ms on captured S7 inputs, session 40). The per-ray form's body stays as it was: on CUDA the same code moved into a
    shared function changed the compiled arithmetic (an H100's step digests of the ray-cast filters differed)."""
    i = wp.tid()
    b = (row0 + i) // n_per
    p = pos_n[i]
    mat = quat_to_mat_wxyz(quat_nb[i])
    blocked = origin_blocked(grid, p)
    for j in range(cloud.shape[1]):
        row = cloud[b, j]
        if row[CR_VALID] == 0.0:
            point_not_received(i, j, want_vertical, residual_out, normal_out, vertical_out)
            continue
        d = mat * row_dir(row)
        cast = no_hit()
        if not blocked:
            cast = cast_unblocked_local(grid, mesh, backend, p, d, step_m, n_bisect)
        t = cast[0]
        grad = wp.vec2(cast[1], cast[2])  # (the DDA's hit triangle: the map read again cost 24 ns a ray)
        if backend != BACKEND_DDA and not is_nan(t):
            hit = p + t * d
            grad = grid_gradient(grid, 1, hit[0], hit[1])
        point_outputs(grid, p, d, row, t, grad, want_vertical, i, j, residual_out, normal_out, vertical_out)
