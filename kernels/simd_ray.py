"""The CPU's heightfield ray casts (the ``dda`` backend) with the rays as SIMD lanes: the ray-casting model's
per-particle kernel (:data:`warptan.kernels.raycast.raycast_residual_rows_kernel`) with its rays cast ``SIMD_LANES`` at
a time by native C++ (``wp.func_native``), the way :mod:`warptan.kernels.simd` sums the points.

One thread per particle, as the Warp kernel. Each lane is one ray of the particle's scan: its direction, its clip to
the terrain's height band and its start at the highest post within its reach
(:func:`~warptan.kernels.raycast.local_band_entry`), then the 2-D DDA over the cells
(:func:`~warptan.kernels.raycast.dda_march`), every lane stepping its own cell each round until all have hit, left the
map or met nodata; a cell a lane's ray may meet is tested with both of its triangles (:func:`~warptan.kernels.raycast.
cell_hit`). The same expressions in the same order as the Warp functions: the same ranges and slopes, bit for bit
(``tests/test_simd.py``); the residuals, normals and heights above the map are then the Warp kernel's own loop over the
cast rays. The Warp kernel is this one's reference.
"""

import warp as wp

from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.likelihood import CR_DIR, CR_VALID, cloud_row, row_dir
from warptan.kernels.raycast import BAND_PAD, BIG, EDGE_EPS, origin_blocked, point_not_received, point_outputs
from warptan.kernels.simd import SIMD_LANES
from warptan.kernels.terrain import BLOCK_CELLS, HeightGrid

wp.set_module_options({"enable_backward": False})

ORDER_BUCKETS = 16
"""Bands of a ray's angle off the sensor's axis (of the squared horizontal part of its unit direction) by which
:func:`dda_casts_simd` orders the rays into lanes."""
MAX_ORDERED = 4096
"""Rays per scan up to which :func:`dda_casts_simd` orders them (its order is an array on the thread's stack)."""

_CONSTANTS = {"SIMD_LANES": SIMD_LANES, "ORDER_BUCKETS": ORDER_BUCKETS, "MAX_ORDERED": MAX_ORDERED, "CR_DIR": CR_DIR,
              "CR_VALID": CR_VALID, "BLOCK_CELLS": BLOCK_CELLS, "BAND_PAD": float(BAND_PAD), "BIG": float(BIG),
              "EDGE_EPS": float(EDGE_EPS)}

# One particle's rays (kernels/raycast.py: cast_unblocked_local for the dda backend: band_interval, local_band_entry,
# dda_march, cell_hit), SIMD_LANES_ rays a round. Per lane: the ray's state in the DDA (its cell ci, cj, the parameter
# tt where it entered it, the next crossings tnu / tnv), act while it is still marching; the results rt (NaN: no hit),
# rgn, rge (the hit triangle's slopes).
_DDA = r"""
    constexpr int L = SIMD_LANES_;
    const float NANF = NAN;
    const int rows = grid.heights.shape[0], cols = grid.heights.shape[1];
    const char* hb = (const char*)grid.heights.data;
    const size_t hs0 = grid.heights.strides[0], hs1 = grid.heights.strides[1];
    const char* cb = (const char*)grid.cell_max.data;
    const size_t cs0 = grid.cell_max.strides[0], cs1 = grid.cell_max.strides[1];
    const float gn0 = grid.n0, ge0 = grid.e0, gdn = grid.dn, gde = grid.de, idn = grid.inv_dn, ide = grid.inv_de;
    const float u_max = static_cast<float>(rows - 1), v_max = static_cast<float>(cols - 1);
    const float z_top = -grid.h_max - BAND_PAD_;
    const float z_bot = -grid.h_min + BAND_PAD_;
    const float o0 = p[0], o1 = p[1], o2 = p[2];
    const float m00 = mat.data[0][0], m01 = mat.data[0][1], m02 = mat.data[0][2];
    const float m10 = mat.data[1][0], m11 = mat.data[1][1], m12 = mat.data[1][2];
    const float m20 = mat.data[2][0], m21 = mat.data[2][1], m22 = mat.data[2][2];
    // local_band_entry's block of the origin (the same for every ray of the particle)
    const float reach = static_cast<float>(BLOCK_CELLS_) * wp::min(gdn, gde);
    const float reach2 = reach * reach;
    float top = 0.0f;
    if (blocked == 0) {
        const int bi = wp::min(static_cast<int>((o0 - gn0) / gdn), rows - 2);
        const int bj = wp::min(static_cast<int>((o1 - ge0) / gde), cols - 2);
        top = *(const float*)((const char*)grid.block_top.data + size_t(bi / BLOCK_CELLS_) * grid.block_top.strides[0]
                              + size_t(bj / BLOCK_CELLS_) * grid.block_top.strides[1]);
    }
    const bool top_ok = !(top > 1.0e37f);
    const float* crow = (const float*)((const char*)cloud.data + size_t(b) * cloud.strides[0]);
    const int cstep = static_cast<int>(cloud.strides[1] / sizeof(float));
    const int m = cloud.shape[1];
    char* trow = (char*)range_out.data + size_t(t) * range_out.strides[0];
    const size_t ts1 = range_out.strides[1];
    char* srow = (char*)slope_out.data + size_t(t) * slope_out.strides[0];
    const size_t ss1 = slope_out.strides[1];
    const int max_it = rows + cols + 4;
    // the rays in lanes by their angle off the sensor's axis, so that a round's lanes march alike (a nadir ray meets
    // the ground in its first cell, an oblique one crosses several): a stable counting sort into ORDER_BUCKETS_
    // bands of the direction's horizontal part (the sensor's frame); scans over MAX_ORDERED_ rays keep their order
    int order[MAX_ORDERED_];
    const bool ordered = m <= MAX_ORDERED_;
    if (ordered) {
        auto band = [&](int j) {  // h2 in [0, 1] for a unit direction; NaN or more: the last band
            const float* row = crow + j * cstep;
            const float h2 = row[CR_DIR_] * row[CR_DIR_] + row[CR_DIR_ + 1] * row[CR_DIR_ + 1];
            return h2 < 1.0f ? static_cast<int>(h2 * static_cast<float>(ORDER_BUCKETS_)) : ORDER_BUCKETS_ - 1;
        };
        int start[ORDER_BUCKETS_ + 1];
        for (int q = 0; q <= ORDER_BUCKETS_; ++q) start[q] = 0;
        for (int j = 0; j < m; ++j) start[band(j) + 1] += 1;
        for (int q = 0; q < ORDER_BUCKETS_; ++q) start[q + 1] += start[q];
        for (int j = 0; j < m; ++j) order[start[band(j)]++] = j;
    }
    for (int j0 = 0; j0 < m; j0 += L) {
        float dx[L], dy[L], dz[L], tt[L], tend[L], tnu[L], tnv[L], tdu[L], tdv[L], rt[L], rgn[L], rge[L];
        int ci[L], cj[L], si[L], sj[L], ray[L];
        bool act[L];
        #pragma clang loop vectorize(enable)
        for (int l = 0; l < L; ++l) {
            const int jl = j0 + l < m ? j0 + l : m - 1;
            const int jc = ordered ? order[jl] : jl;
            const float* row = crow + jc * cstep;
            const bool valid = (j0 + l < m) & (row[CR_VALID_] != 0.0f) & (blocked == 0);
            // wp::normalize(mat * row_dir(row)), written out (a struct returned in the loop kept it scalar)
            const float c0 = row[CR_DIR_], c1 = row[CR_DIR_ + 1], c2 = row[CR_DIR_ + 2];
            const float r0 = m00 * c0 + m01 * c1 + m02 * c2;
            const float r1 = m10 * c0 + m11 * c1 + m12 * c2;
            const float r2 = m20 * c0 + m21 * c1 + m22 * c2;
            const float len = wp::sqrt(r0 * r0 + r1 * r1 + r2 * r2);
            const bool unit = len > 0.0f;
            const float d0 = unit ? r0 / len : 0.0f, d1 = unit ? r1 / len : 0.0f, d2 = unit ? r2 / len : 0.0f;
            // band_interval
            const float ztb = d2 > 0.0f ? z_top : z_bot, zbt = d2 > 0.0f ? z_bot : z_top;
            const float tin0 = wp::max(0.0f, (ztb - o2) / d2);
            const float tin = d2 != 0.0f ? tin0 : 0.0f;
            const float tout = d2 != 0.0f ? (zbt - o2) / d2 : ((o2 < z_top || o2 > z_bot) ? -1.0f : BIG_);
            // local_band_entry
            const bool near = !((d0 * d0 + d1 * d1) * tout * tout > reach2);
            const float tloc = wp::max(tin, (-top - BAND_PAD_ - o2) / d2);
            const float t0 = (d2 > 0.0f && near && top_ok) ? tloc : tin;
            // dda_march's start
            const float u = (o0 + t0 * d0 - gn0) / gdn;
            const float v = (o1 + t0 * d1 - ge0) / gde;
            const bool inside = u >= 0.0f && u <= u_max && v >= 0.0f && v <= v_max;
            const bool go = valid && !(tin > tout) && inside;
            const int i = go ? wp::min(static_cast<int>(wp::floor(u)), rows - 2) : 0;
            const int k = go ? wp::min(static_cast<int>(wp::floor(v)), cols - 2) : 0;
            const float du = d0 * idn, dv = d1 * ide;
            tnu[l] = du > 0.0f ? t0 + (static_cast<float>(i + 1) - u) / du
                               : (du < 0.0f ? t0 + (static_cast<float>(i) - u) / du : BIG_);
            tdu[l] = du > 0.0f ? 1.0f / du : (du < 0.0f ? -1.0f / du : BIG_);
            tnv[l] = dv > 0.0f ? t0 + (static_cast<float>(k + 1) - v) / dv
                               : (dv < 0.0f ? t0 + (static_cast<float>(k) - v) / dv : BIG_);
            tdv[l] = dv > 0.0f ? 1.0f / dv : (dv < 0.0f ? -1.0f / dv : BIG_);
            si[l] = du < 0.0f ? -1 : 1;
            sj[l] = dv < 0.0f ? -1 : 1;
            dx[l] = d0; dy[l] = d1; dz[l] = d2;
            tt[l] = t0; tend[l] = tout; ci[l] = i; cj[l] = k; act[l] = go; ray[l] = jc;
            rt[l] = NANF; rgn[l] = 0.0f; rge[l] = 0.0f;
        }
        for (int it = 0; it < max_it; ++it) {
            bool any = false;
            for (int l = 0; l < L; ++l) any |= act[l];
            if (!any) break;
            #pragma clang loop vectorize(enable)
            for (int l = 0; l < L; ++l) {
                const bool a = act[l];
                const int i = ci[l], k = cj[l];
                const float d0 = dx[l], d1 = dy[l], d2 = dz[l], t0 = tt[l], nu = tnu[l], nv = tnv[l];
                const float tce = wp::min(wp::min(nu, nv), tend[l]);
                const float z_low = wp::max(o2 + t0 * d2, o2 + tce * d2);
                const float cmax = *(const float*)(cb + size_t(i) * cs0 + size_t(k) * cs1);
                const bool cand = -z_low <= cmax + BAND_PAD_;
                const bool nodata = cand && cmax > 1.0e37f;
                // cell_hit
                const char* post = hb + size_t(i) * hs0 + size_t(k) * hs1;
                const float h00 = *(const float*)post, h01 = *(const float*)(post + hs1);
                const float h10 = *(const float*)(post + hs0), h11 = *(const float*)(post + hs0 + hs1);
                const float ca = o0 - (gn0 + static_cast<float>(i) * gdn);
                const float cb_ = o1 - (ge0 + static_cast<float>(k) * gde);
                const float sua = (h10 - h00) * idn, sva = (h11 - h10) * ide;
                const float fa = d2 + d0 * sua + d1 * sva;
                const float ta = -(o2 + h00 + ca * sua + cb_ * sva) / fa;
                const float uua = (ca + ta * d0) * idn, vva = (cb_ + ta * d1) * ide;
                const bool hita = fa > 0.0f && ta >= 0.0f && vva >= -EDGE_EPS_ && uua <= 1.0f + EDGE_EPS_
                                  && uua >= vva - EDGE_EPS_;
                const float sub = (h11 - h01) * idn, svb = (h01 - h00) * ide;
                const float fb = d2 + d0 * sub + d1 * svb;
                const float tb = -(o2 + h00 + ca * sub + cb_ * svb) / fb;
                const float uub = (ca + tb * d0) * idn, vvb = (cb_ + tb * d1) * ide;
                const bool hitb = fb > 0.0f && tb >= 0.0f && (!hita || tb < ta) && uub >= -EDGE_EPS_
                                  && vvb <= 1.0f + EDGE_EPS_ && vvb >= uub - EDGE_EPS_;
                const bool hit = cand && !nodata && (hita || hitb);
                rt[l] = (a && hit) ? (hitb ? tb : ta) : rt[l];
                rgn[l] = (a && hit) ? (hitb ? sub : sua) : rgn[l];
                rge[l] = (a && hit) ? (hitb ? svb : sva) : rge[l];
                const bool stop = nodata || hit || tce >= tend[l];
                // every lane steps on, done or not (a done lane's steps write nothing): the next cell depends on the
                // crossings alone, not on this cell's test, so the next round's reads need not wait for it
                const bool step_u = nu < nv;
                const int ni = step_u ? i + si[l] : i, nk = step_u ? k : k + sj[l];
                const bool left = ni < 0 || ni > rows - 2 || nk < 0 || nk > cols - 2;
                tt[l] = step_u ? nu : nv;
                tnu[l] = step_u ? nu + tdu[l] : nu;
                tnv[l] = step_u ? nv : nv + tdv[l];
                act[l] = a && !stop && !left;
                ci[l] = ni < 0 ? 0 : (ni > rows - 2 ? rows - 2 : ni);
                cj[l] = nk < 0 ? 0 : (nk > cols - 2 ? cols - 2 : nk);
            }
        }
        const int n_lanes = m - j0 < L ? m - j0 : L;
        for (int l = 0; l < n_lanes; ++l) {
            *(float*)(trow + size_t(ray[l]) * ts1) = rt[l];
            *(wp::vec3*)(srow + size_t(ray[l]) * ss1) = wp::vec3(rgn[l], rge[l], 0.0f);
        }
    }
"""


def _snippet() -> str:
    snippet = _DDA
    for name, value in _CONSTANTS.items():
        snippet = snippet.replace(name + "_", f"{value!r}f" if isinstance(value, float) else str(value))
    return snippet


@wp.func_native(_snippet())
def dda_casts_simd(grid: HeightGrid, p: wp.vec3, mat: wp.mat33, blocked: int, cloud: wp.array2d(dtype=cloud_row),
                   b: int, t: int, range_out: wp.array2d(dtype=wp.float32), slope_out: wp.array2d(dtype=wp.vec3)):
    """Particle ``t`` (origin ``p``, attitude ``mat``; ``blocked``: its origin cannot cast, :func:`~warptan.kernels.
    raycast.origin_blocked`) of filter ``b``: each point's ray cast by DDA, its range ``range_out[t, j]`` (m; NaN: no
    hit, not received) and the hit triangle's slopes ``slope_out[t, j] = (∂h/∂n, ∂h/∂e, 0)``."""
    ...


@wp.kernel
def raycast_residual_rows_simd_kernel(
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
    """:data:`~warptan.kernels.raycast.raycast_residual_rows_kernel` for the ``dda`` backend (``mesh``, ``backend``,
    ``step_m`` and ``n_bisect`` unused), its rays cast in lanes (:func:`dda_casts_simd`, which leaves each range in
    ``residual_out`` and each slope pair in ``normal_out``), then its outputs point by point (:func:`~warptan.kernels.
    raycast.point_outputs`)."""
    i = wp.tid()
    b = (row0 + i) // n_per
    p = pos_n[i]
    mat = quat_to_mat_wxyz(quat_nb[i])
    dda_casts_simd(grid, p, mat, int(origin_blocked(grid, p)), cloud, b, i, residual_out, normal_out)
    for j in range(cloud.shape[1]):
        row = cloud[b, j]
        if row[CR_VALID] == 0.0:
            point_not_received(i, j, want_vertical, residual_out, normal_out, vertical_out)
            continue
        slopes = normal_out[i, j]
        point_outputs(grid, p, mat * row_dir(row), row, residual_out[i, j], wp.vec2(slopes[0], slopes[1]),
                      want_vertical, i, j, residual_out, normal_out, vertical_out)
