"""The CPU's per-point sums with the points as SIMD lanes: the sliding model (:mod:`warptan.kernels.sliding`) and the
ray-casting model's reduction (:data:`warptan.kernels.likelihood.reduce_loglik_kernels`).

One thread per particle, as the Warp kernels on the CPU, but the loop over the points is native C++
(``wp.func_native``) that takes ``SIMD_LANES`` points at a time, each lane with its own partial sums: the compiler
turns the lanes into vector instructions (the map reads into gathers, the branches into selects). Each point's
values (the sliding model's placed point, map height and gradient and residual; σ², Jacobians, the gross-miss test)
are the same expressions in the same order as the Warp kernels', and the same float32 bits (the residuals are
identical, ``tests/test_simd.py``); the sums are added lane by lane, and the lanes in order at the end, which is
another order than the Warp kernels' point by point: the sums differ in their last bits, the same on every run and
every thread split. The Warp kernels are these ones' reference.

Why: on the CPU the sliding Warp kernel's scalar loop cost 46 ns per (particle, point) on captured S8 inputs, one
thread (the sums of the attitude and position information alone ~30 ns, the map read ~11 ns); the lanes took it to
15 ns (2-core Xeon with AVX-512, ``-march=native``: Warp's CPU default).

Covered: every likelihood (the Student-t's logs in a scalar pass after each group of lanes), both surfaces, gross
misses, points off the map, on nodata, not received or not hit, and the map-error modes of a stated map error (each
used point's whitened residual and Jacobians times its table row, the modes as a vector: with them in the Warp
kernels the CPU's S8 update over a world took 2.4× the no-mode one, S7's 3×; CPU, 30 s runs).
"""

import re

import warp as wp

from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.likelihood import (
    ACC_LEN,
    CR_DIR,
    CR_POINT,
    CR_RANGE,
    CR_VALID,
    LIK_PAPER,
    LIK_STUDENT,
    MAX_MODES,
    RAY_MAP_GAIN_MAX,
    VAR_RATIO_FOLD_MAX,
    VAR_RATIO_FOLD_MIN,
    LikParams,
    acc_set_modes,
    acc_store,
    acc_unpack,
    acc_vec,
    cloud_row,
    mode_post,
    modes_init,
    modes_sums_vec,
    modes_unpack,
    modes_vec,
)
from warptan.kernels.terrain import HeightGrid

wp.set_module_options({"enable_backward": False})

SIMD_LANES = 8
"""Points summed side by side (one AVX2 register of float32; 16 measured 25 % slower on AVX-512)."""

# The C++ pieces of the kernels' point loops. Sums s[k][lane] indexed as acc_vec (kernels/likelihood.py: acc_pack): 0
# received, 1 predictable, 2 Σ|r|, 3-5 Σ|r| w (the axis weights), 7 Σ log-density folds (and the Student-t's
# densities), 8 Σ min(z², k²), 9-14 Λ (00 11 22 01 02 12), 15-17 b, 18-23 Σ GGᵀ (as Λ), 24-32 Σ HGᵀ (row-major),
# 33-35 Σ G r, 36-37 the gross misses' log-densities and min(z_v, k)², 38 gross misses, 39 Σ z²; 6 is the last
# predictable residual. A model's point (_SLIDING_POINT, _RAY_POINT) defines, per lane: valid (a received point), res
# (NaN where not predictable), var (σ_j², m²), miss (a gross miss, gross_miss), zg (its z_v, acc_gated), aw0-2 (the
# axis weights), hj0-2 and gj0-2 (the Jacobians H, G).
_HEAD = r"""
    constexpr int L = SIMD_LANES_;
    constexpr int NS = ACC_LEN_;
    const float NANF = NAN;
    float s[NS][L];
    float ratio[L], lastj[L], lastv[L], zbuf[L], zgbuf[L], resbuf[L];
    bool usebuf[L], missbuf[L];
    for (int k = 0; k < NS; ++k) for (int l = 0; l < L; ++l) s[k][l] = 0.0f;
    for (int l = 0; l < L; ++l) { ratio[l] = 1.0f; lastj[l] = -1.0f; lastv[l] = 0.0f; }

    const int lik = params.lik;
    const float k2 = params.k_out * params.k_out, var0 = params.sigma * params.sigma, nu = params.nu;
    const bool not_world = lik != LIK_PAPER_ && (params.sigma_err > 0.0f || params.sigma_map > 0.0f);
    const float sr2 = params.sigma_range * params.sigma_range, sm2 = params.sigma_map * params.sigma_map;
    const float se2 = params.sigma_err * params.sigma_err;
    const float info_on = lik != LIK_PAPER_ ? 1.0f : 0.0f;
    const float* crow = (const float*)((const char*)cloud.data + size_t(b) * cloud.strides[0]);
    const int cstep = static_cast<int>(cloud.strides[1] / sizeof(float));
    const int m = cloud.shape[1];
    const float m00 = mat.data[0][0], m01 = mat.data[0][1], m02 = mat.data[0][2];
    const float m10 = mat.data[1][0], m11 = mat.data[1][1], m12 = mat.data[1][2];
    const float m20 = mat.data[2][0], m21 = mat.data[2][1], m22 = mat.data[2][2];
"""

_LOOP = r"""
    for (int j0 = 0; j0 < m; j0 += L) {
        #pragma clang loop vectorize(enable)
        for (int l = 0; l < L; ++l) {
            const int j = j0 + l;
            const int jc = j < m ? j : m - 1;  // the tail's spare lanes read the last point
            const float* row = crow + jc * cstep;
            const bool valid = (j < m) & (row[CR_VALID_] != 0.0f);
            POINT_
            resbuf[l] = res;
            const bool ok = res == res;
            const bool gated = ok && miss;
            const bool use = ok && !miss;
            usebuf[l] = use;
            missbuf[l] = gated;
            const float r = use ? res : 0.0f;
            const float iv = use ? 1.0f / var : 0.0f;
            const float z2 = r * r * iv;
            zbuf[l] = z2;
            const float wi = iv * info_on;
            const float w = lik == LIK_STUDENT_ ? wi * (nu + 1.0f) / (nu + z2) : wi;  // the Student-t's weight
            const float h0u = use ? hj0 : 0.0f, h1u = use ? hj1 : 0.0f, h2u = use ? hj2 : 0.0f;
            const float g0u = use ? gj0 : 0.0f, g1u = use ? gj1 : 0.0f, g2u = use ? gj2 : 0.0f;
            MODES_LANE_
            const float zq = gated ? (zg * params.sigma / params.sigma) * (zg * params.sigma / params.sigma) : 0.0f;
            zgbuf[l] = zq;
            s[0][l] += valid ? 1.0f : 0.0f;
            s[1][l] += use ? 1.0f : 0.0f;
            s[38][l] += gated ? 1.0f : 0.0f;
            const float ra = wp::abs(r);
            s[2][l] += ra;
            s[3][l] += ra * aw0; s[4][l] += ra * aw1; s[5][l] += ra * aw2;
            s[8][l] += wp::min(z2, k2);
            s[39][l] += z2;
            s[36][l] += lik == LIK_STUDENT_ ? 0.0f : -0.5f * zq;
            s[37][l] += gated ? zg * zg : 0.0f;
            ratio[l] *= (use && var != var0) ? var / var0 : 1.0f;
            lastj[l] = use ? static_cast<float>(j) : lastj[l];
            lastv[l] = use ? res : lastv[l];
            const float h0 = h0u * w, h1 = h1u * w, h2 = h2u * w;
            const float e0 = g0u * w, e1 = g1u * w, e2 = g2u * w;
            s[9][l] += h0 * h0u; s[10][l] += h1 * h1u; s[11][l] += h2 * h2u;
            s[12][l] += h0 * h1u; s[13][l] += h0 * h2u; s[14][l] += h1 * h2u;
            s[15][l] += h0 * r; s[16][l] += h1 * r; s[17][l] += h2 * r;
            s[18][l] += e0 * g0u; s[19][l] += e1 * g1u; s[20][l] += e2 * g2u;
            s[21][l] += e0 * g1u; s[22][l] += e0 * g2u; s[23][l] += e1 * g2u;
            s[24][l] += h0 * g0u; s[25][l] += h0 * g1u; s[26][l] += h0 * g2u;
            s[27][l] += h1 * g0u; s[28][l] += h1 * g1u; s[29][l] += h1 * g2u;
            s[30][l] += h2 * g0u; s[31][l] += h2 * g1u; s[32][l] += h2 * g2u;
            s[33][l] += e0 * r; s[34][l] += e1 * r; s[35][l] += e2 * r;
        }
        const int n_lanes = m - j0 < L ? m - j0 : L;
        STORE_RESIDUALS_
        MODES_ACCUM_
        if (lik == LIK_STUDENT_) {  // the Student-t's log-densities (point_loglik_z2); the Gaussian's -z²/2 below
            for (int l = 0; l < L; ++l) {
                if (usebuf[l]) s[7][l] += -0.5f * (nu + 1.0f) * wp::log(1.0f + zbuf[l] / nu);
                if (missbuf[l]) s[36][l] += -0.5f * (nu + 1.0f) * wp::log(1.0f + zgbuf[l] / nu);
            }
        }
        for (int l = 0; l < L; ++l) {  // fold -log(σ_j / σ) into the log-density before the product leaves float32
            if (!(ratio[l] > VAR_RATIO_FOLD_MIN_ && ratio[l] < VAR_RATIO_FOLD_MAX_)) {
                s[7][l] -= 0.5f * wp::log(ratio[l]);
                ratio[l] = 1.0f;
            }
        }
    }
    wp::vec_t<NS, wp::float32> out;
    float last_j = -1.0f;
    for (int l = 0; l < L; ++l) {
        for (int k = 0; k < NS; ++k) out[k] += s[k][l];
        out[7] -= 0.5f * wp::log(ratio[l]);
        if (lastj[l] > last_j) { last_j = lastj[l]; out[6] = lastv[l]; }
    }
    if (lik != LIK_STUDENT_) out[7] += -0.5f * out[39];
    MODES_STORE_
    return out;
"""

# The sliding prediction (kernels/sliding.py: sliding_loglik_kernel, sliding_var, sliding_jacobian, and the map reads
# of kernels/terrain.py): the point placed with the particle's pose, w = p + R c, the map's height and gradient
# under it, the residual c_z - ĉ_z; n_s = Rᵀ ∇F, σ², H, G = -g_z ∇F. Its height above the map is unknown: a gross
# miss scores k_out.
_SLIDING_HEAD = r"""
    const int rows = grid.heights.shape[0], cols = grid.heights.shape[1];
    const float u_max = static_cast<float>(rows - 1), v_max = static_cast<float>(cols - 1);
    const char* hbase = (const char*)grid.heights.data;
    const size_t hs0 = grid.heights.strides[0], hs1 = grid.heights.strides[1];
    const bool noiseless = params.sigma_range <= 0.0f;
    const float gabs = wp::max(wp::abs(m22), 0.2f);
    const float px = pos[0], py = pos[1], pz = pos[2];
    const float gn0 = grid.n0, ge0 = grid.e0, gdn = grid.dn, gde = grid.de, idn = grid.inv_dn, ide = grid.inv_de;
    char* rrow = (char*)residual_out.data + size_t(t) * residual_out.strides[0];
    const size_t rs1 = residual_out.strides[1];
"""
_SLIDING_POINT = r"""
            const float c0 = row[CR_POINT_], c1 = row[CR_POINT_ + 1], c2 = row[CR_POINT_ + 2];
            const float w0 = px + (m00 * c0 + m01 * c1 + m02 * c2);
            const float w1 = py + (m10 * c0 + m11 * c1 + m12 * c2);
            const float w2 = pz + (m20 * c0 + m21 * c1 + m22 * c2);
            const float u = (w0 - gn0) / gdn;
            const float v = (w1 - ge0) / gde;
            const bool inside = u >= 0.0f && u <= u_max && v >= 0.0f && v <= v_max;
            const int i = inside ? wp::min(static_cast<int>(u), rows - 2) : 0;
            const int k = inside ? wp::min(static_cast<int>(v), cols - 2) : 0;
            const float fu = u - static_cast<float>(i), fv = v - static_cast<float>(k);
            const char* post = hbase + size_t(i) * hs0 + size_t(k) * hs1;
            const float h00 = *(const float*)post, h01 = *(const float*)(post + hs1);
            const float h10 = *(const float*)(post + hs0), h11 = *(const float*)(post + hs0 + hs1);
            float h, g0, g1;
            if (surface == 0) {
                h = (1.0f - fu) * ((1.0f - fv) * h00 + fv * h01) + fu * ((1.0f - fv) * h10 + fv * h11);
                g0 = ((1.0f - fv) * (h10 - h00) + fv * (h11 - h01)) * idn;
                g1 = ((1.0f - fu) * (h01 - h00) + fu * (h11 - h10)) * ide;
            } else {  // triangle (i,j) (i+1,j) (i+1,j+1) where fu >= fv, else (i,j) (i,j+1) (i+1,j+1)
                const bool up = fu >= fv;
                const float a0 = up ? fu : fv, a1 = up ? fv : fu, mid = up ? h10 : h01;
                const float d0 = mid - h00, d1 = h11 - mid;
                const float all = h00 + h10 + h01 + h11;
                h = all == all ? h00 + a0 * d0 + a1 * d1 : NANF;
                g0 = (up ? d0 : d1) * idn;
                g1 = (up ? d1 : d0) * ide;
            }
            h = inside ? h : NANF;
            const float gap = -h - w2;
            const float res = valid ? -gap * m22 : NANF;
            const float n0 = m00 * g0 + m10 * g1 + m20;
            const float n1 = m01 * g0 + m11 * g1 + m21;
            const float n2 = m02 * g0 + m12 * g1 + m22;
            const float slope_dot = n0 * row[CR_DIR_] + n1 * row[CR_DIR_ + 1] + n2 * row[CR_DIR_ + 2];
            const float geo = params.n_modes > 0 ? 1.0f : wp::max(wp::abs(slope_dot), 0.25f);  // sliding_var
            const float var = noiseless ? var0 : gabs * gabs * (sr2 * geo * geo + sm2);
            const bool miss = not_world && res * res > k2 * (var + se2);
            const float zg = params.k_out;
            const float aw0 = 1.0f, aw1 = 1.0f, aw2 = 1.0f;
            const float hj0 = -gap * m21 + m22 * (n1 * c2 - n2 * c1);
            const float hj1 = gap * m20 + m22 * (n2 * c0 - n0 * c2);
            const float hj2 = m22 * (n0 * c1 - n1 * c0);
            const float gj0 = g0 * -m22, gj1 = g1 * -m22, gj2 = -m22;
"""

# A cast ray's residual (kernels/likelihood.py: reduce_loglik_kernel, ray_jacobians, ray_var, ray_nominal_gain,
# gross_miss, acc_gated): the range residual and the scaled normal s at the hit from the casts, H = t (Rᵀs) × d, G =
# -s, the axis weights |d|; a gross miss scores its point's height above the map.
_RAY_HEAD = r"""
    const float* res_row = (const float*)((const char*)residual.data + size_t(t) * residual.strides[0]);
    const int res_step = static_cast<int>(residual.strides[1] / sizeof(float));
    const float* nrm_row = (const float*)((const char*)normal.data + size_t(t) * normal.strides[0]);
    const int nrm_step = static_cast<int>(normal.strides[1] / sizeof(float));
    const float* vert_row = (const float*)((const char*)vertical.data + size_t(t) * vertical.strides[0]);
    const int vert_step = static_cast<int>(vertical.strides[1] / sizeof(float));
    const bool fixed = params.sigma_range <= 0.0f || (params.sigma_map <= 0.0f && params.sigma_err <= 0.0f);
    const bool stated = params.sigma_err > 0.0f;
    const float vg0 = params.sigma_err * params.sigma_err + params.sigma_map * params.sigma_map;
"""
_RAY_POINT = r"""
            const float res = valid ? res_row[jc * res_step] : NANF;
            const float* nrm = nrm_row + jc * nrm_step;
            const float sn0 = nrm[0], sn1 = nrm[1], sn2 = nrm[2];
            const float d0 = row[CR_DIR_], d1 = row[CR_DIR_ + 1], d2 = row[CR_DIR_ + 2];
            const float u_down = m20 * d0 + m21 * d1 + m22 * d2;
            const float n0 = m00 * sn0 + m10 * sn1 + m20 * sn2;
            const float n1 = m01 * sn0 + m11 * sn1 + m21 * sn2;
            const float n2 = m02 * sn0 + m12 * sn1 + m22 * sn2;
            const float tr = row[CR_RANGE_] - res;
            const float hj0 = tr * (n1 * d2 - n2 * d1);
            const float hj1 = tr * (n2 * d0 - n0 * d2);
            const float hj2 = tr * (n0 * d1 - n1 * d0);
            const float gj0 = -sn0, gj1 = -sn1, gj2 = -sn2;
            const float gs = sn2 != 0.0f ? wp::min(wp::abs(sn2), RAY_MAP_GAIN_MAX_) : RAY_MAP_GAIN_MAX_;
            const float gain = 1.0f / wp::max(u_down, 0.1f);
            const float excess = gs - gain;
            const float var_m = sr2 + sm2 * gs * gs;
            const float var = fixed ? var0 : (stated ? var_m + se2 * excess * excess : var_m);
            const float e = params.sigma_err * gain;
            const bool miss = not_world && res * res > k2 * (var + e * e);
            const float vert = not_world ? vert_row[jc * vert_step] : NANF;
            const float vg = vg0 + (params.sigma_range / gain) * (params.sigma_range / gain);
            const float zv = wp::min(wp::abs(vert) / wp::sqrt(wp::max(vg, 1.0e-12f)), params.k_out);
            const float zg = vert == vert ? zv : params.k_out;
            const float aw0 = wp::abs(d0), aw1 = wp::abs(d1), aw2 = wp::abs(d2);
"""


# The map-error modes' projections (kernels/likelihood.py: acc_modes, with a stated map error): a point the particle
# uses (predictable, not a gross miss) adds its table row u_j times its whitened residual r_j/σ_j and Jacobians H_j/σ_j,
# G_j/σ_j to 7 × MAX_MODES sums. The lanes keep the whitened values; after each group of lanes the points are added
# in order, each one's row as a vector over the modes (the same products in the same order as acc_modes). The sums
# leave through ``modes_out[t]`` in modes_pack's layout.
_MODES_HEAD = r"""
    constexpr int MM = MAX_MODES_;
    constexpr int MB = 8;  // modes per register block
    float mp[MM], mh0s[MM], mh1s[MM], mh2s[MM], mg0s[MM], mg1s[MM], mg2s[MM];
    for (int i = 0; i < MM; ++i) {
        mp[i] = 0.0f; mh0s[i] = 0.0f; mh1s[i] = 0.0f; mh2s[i] = 0.0f; mg0s[i] = 0.0f; mg1s[i] = 0.0f; mg2s[i] = 0.0f;
    }
    float mz[L], mh0[L], mh1[L], mh2[L], mg0[L], mg1[L], mg2[L];
    const char* ubase = (const char*)modes.data;
    const size_t ustride = modes.strides[0];
"""
_MODES_LANE = r"""
            const float isd = use ? 1.0f / wp::sqrt(var) : 0.0f;
            mz[l] = r * isd;
            mh0[l] = h0u * isd; mh1[l] = h1u * isd; mh2[l] = h2u * isd;
            mg0[l] = g0u * isd; mg1[l] = g1u * isd; mg2[l] = g2u * isd;
"""
_MODES_ACCUM = r"""
        if (lik != LIK_PAPER_) {
            for (int i0 = 0; i0 < MM; i0 += MB) {
                float ap[MB], ah0[MB], ah1[MB], ah2[MB], ag0[MB], ag1[MB], ag2[MB];
                for (int i = 0; i < MB; ++i) {
                    ap[i] = mp[i0 + i]; ah0[i] = mh0s[i0 + i]; ah1[i] = mh1s[i0 + i]; ah2[i] = mh2s[i0 + i];
                    ag0[i] = mg0s[i0 + i]; ag1[i] = mg1s[i0 + i]; ag2[i] = mg2s[i0 + i];
                }
                for (int l = 0; l < n_lanes; ++l) {
                    if (!usebuf[l]) continue;
                    const float* u = (const float*)(ubase + size_t(j0 + l) * ustride) + i0;
                    const float z = mz[l], a0 = mh0[l], a1 = mh1[l], a2 = mh2[l], e0 = mg0[l], e1 = mg1[l], e2 = mg2[l];
                    #pragma clang loop vectorize(enable)
                    for (int i = 0; i < MB; ++i) {
                        const float ui = u[i];
                        ap[i] += ui * z;
                        ah0[i] += ui * a0; ah1[i] += ui * a1; ah2[i] += ui * a2;
                        ag0[i] += ui * e0; ag1[i] += ui * e1; ag2[i] += ui * e2;
                    }
                }
                for (int i = 0; i < MB; ++i) {
                    mp[i0 + i] = ap[i]; mh0s[i0 + i] = ah0[i]; mh1s[i0 + i] = ah1[i]; mh2s[i0 + i] = ah2[i];
                    mg0s[i0 + i] = ag0[i]; mg1s[i0 + i] = ag1[i]; mg2s[i0 + i] = ag2[i];
                }
            }
        }
"""
_MODES_STORE = r"""
    float* mo = (float*)((char*)modes_out.data + size_t(t) * modes_out.strides[0]);
    for (int i = 0; i < MM; ++i) {
        mo[i] = mp[i];
        mo[MM + 3 * i] = mh0s[i]; mo[MM + 3 * i + 1] = mh1s[i]; mo[MM + 3 * i + 2] = mh2s[i];
        mo[4 * MM + 3 * i] = mg0s[i]; mo[4 * MM + 3 * i + 1] = mg1s[i]; mo[4 * MM + 3 * i + 2] = mg2s[i];
    }
"""


_CONSTANTS = {  # the Python constants the C++ reads (as NAME_), so that both change together
    "SIMD_LANES": SIMD_LANES, "ACC_LEN": ACC_LEN, "LIK_PAPER": LIK_PAPER, "LIK_STUDENT": LIK_STUDENT,
    "CR_POINT": CR_POINT, "CR_DIR": CR_DIR, "CR_RANGE": CR_RANGE, "CR_VALID": CR_VALID,
    "VAR_RATIO_FOLD_MIN": float(VAR_RATIO_FOLD_MIN), "VAR_RATIO_FOLD_MAX": float(VAR_RATIO_FOLD_MAX),
    "RAY_MAP_GAIN_MAX": float(RAY_MAP_GAIN_MAX), "MAX_MODES": MAX_MODES,
}
_STORE = "for (int l = 0; l < n_lanes; ++l) *(float*)(rrow + size_t(j0 + l) * rs1) = resbuf[l];"


def _snippet(head: str, point: str, store: str, modes: bool = False) -> str:
    """A kernel's point loop (the common head, ``head``, the loop with its model's ``point``; ``store`` writes the
    residuals; ``modes``: the map-error modes' sums too), each sum ``s[k]`` its own array of lanes, ``s<k>[L]``: with
    one 2-D array of all the sums the compiler kept the loop scalar (LLVM's vectoriser could not bound the accesses
    against the cloud's loads)."""
    sums = range(ACC_LEN)
    loop = _LOOP.replace("POINT_", point.strip()).replace("STORE_RESIDUALS_", store)
    loop = loop.replace("MODES_LANE_", _MODES_LANE.strip() if modes else "")
    loop = loop.replace("MODES_ACCUM_", _MODES_ACCUM.strip() if modes else "")
    loop = loop.replace("MODES_STORE_", _MODES_STORE.strip() if modes else "")
    snippet = _HEAD + (_MODES_HEAD if modes else "") + head + loop
    snippet = snippet.replace("    float s[NS][L];\n", "    float " + ", ".join(f"s{k}[L]" for k in sums) + ";\n")
    snippet = snippet.replace("for (int k = 0; k < NS; ++k) for (int l = 0; l < L; ++l) s[k][l] = 0.0f;",
                              "for (int l = 0; l < L; ++l) { " + " ".join(f"s{k}[l] = 0.0f;" for k in sums) + " }")
    snippet = snippet.replace("for (int k = 0; k < NS; ++k) out[k] += s[k][l];",
                              " ".join(f"out[{k}] += s{k}[l];" for k in sums))
    snippet = re.sub(r"\bs\[(\d+)\]\[l\]", r"s\1[l]", snippet)
    assert re.search(r"\bs\[", snippet) is None
    for name, value in _CONSTANTS.items():
        snippet = snippet.replace(name + "_", f"{value!r}f" if isinstance(value, float) else str(value))
    return snippet


@wp.func_native(_snippet(_SLIDING_HEAD, _SLIDING_POINT, _STORE))
def sliding_sums_simd(grid: HeightGrid, surface: int, pos: wp.vec3, mat: wp.mat33,
                      cloud: wp.array2d(dtype=cloud_row), b: int, t: int, params: LikParams,
                      residual_out: wp.array2d(dtype=wp.float32)) -> acc_vec:
    """Particle ``t`` (pose ``pos``, ``mat``) of filter ``b``: its residuals ``residual_out[t, :]`` (m, NaN where not
    predictable) and the running sums of its points as :func:`warptan.kernels.likelihood.acc_pack` packs them."""
    ...


@wp.func_native(_snippet(_RAY_HEAD, _RAY_POINT, ""))
def ray_sums_simd(residual: wp.array2d(dtype=wp.float32), normal: wp.array2d(dtype=wp.vec3),
                  vertical: wp.array2d(dtype=wp.float32), mat: wp.mat33, cloud: wp.array2d(dtype=cloud_row), b: int,
                  t: int, params: LikParams) -> acc_vec:
    """Particle ``t`` (attitude ``mat``) of filter ``b``: the running sums of its cast rays (``residual[t, :]``,
    ``normal[t, :]``, ``vertical[t, :]``) as :func:`warptan.kernels.likelihood.acc_pack` packs them."""
    ...


@wp.func_native(_snippet(_SLIDING_HEAD, _SLIDING_POINT, _STORE, modes=True))
def sliding_sums_modes_simd(grid: HeightGrid, surface: int, pos: wp.vec3, mat: wp.mat33,
                            cloud: wp.array2d(dtype=cloud_row), b: int, t: int, params: LikParams,
                            residual_out: wp.array2d(dtype=wp.float32), modes: wp.array(dtype=modes_vec),
                            modes_out: wp.array(dtype=modes_sums_vec)) -> acc_vec:
    """:func:`sliding_sums_simd` with the map-error modes' sums (the table ``modes``) into ``modes_out[t]``."""
    ...


@wp.func_native(_snippet(_RAY_HEAD, _RAY_POINT, "", modes=True))
def ray_sums_modes_simd(residual: wp.array2d(dtype=wp.float32), normal: wp.array2d(dtype=wp.vec3),
                        vertical: wp.array2d(dtype=wp.float32), mat: wp.mat33, cloud: wp.array2d(dtype=cloud_row),
                        b: int, t: int, params: LikParams, modes: wp.array(dtype=modes_vec),
                        modes_out: wp.array(dtype=modes_sums_vec)) -> acc_vec:
    """:func:`ray_sums_simd` with the map-error modes' sums (the table ``modes``) into ``modes_out[t]``."""
    ...


def _sliding_simd(with_modes: bool):
    @wp.kernel
    def sliding_loglik_simd_kernel(
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
        mode_sums: wp.array(dtype=modes_sums_vec),
        residual_out: wp.array2d(dtype=wp.float32),
        err_out: wp.array(dtype=wp.float32),
        loglik_out: wp.array(dtype=wp.float32),
        nis_out: wp.array(dtype=wp.float32),
        n_valid_out: wp.array(dtype=wp.int32),
        lam_out: wp.array(dtype=wp.mat33),
        info_out: wp.array(dtype=wp.vec3),
        post_out: wp.array(dtype=modes_vec),
    ):
        """The sliding model, one thread per particle on the CPU: the outputs of :data:`warptan.kernels.sliding.
        sliding_loglik_kernels` ``[False, modes]``; with modes ``mode_sums`` holds each particle's mode sums between
        the point loop and the modes' update (scratch, a row per particle), without them it and the mode arrays are
        unused."""
        t = wp.tid()
        b = (row0 + t) // n_per
        mat = quat_to_mat_wxyz(quat_nb[t])
        macc = modes_init()
        if wp.static(with_modes):
            acc = acc_unpack(sliding_sums_modes_simd(grid, surface, pos_n[t], mat, cloud, b, t, params, residual_out,
                                                     modes, mode_sums))
            macc = acc_set_modes(modes_unpack(mode_sums[t]), modes, cloud.shape[1], mode_mean[t], mode_var[b])
            post_out[t] = mode_post(macc, modes, cloud.shape[1])
        else:
            acc = acc_unpack(sliding_sums_simd(grid, surface, pos_n[t], mat, cloud, b, t, params, residual_out))
        acc_store(t, acc, macc, params, att_cov[b], err_out, loglik_out, nis_out, n_valid_out, lam_out, info_out)

    return sliding_loglik_simd_kernel


def _reduce_simd(with_modes: bool):
    @wp.kernel
    def reduce_loglik_simd_kernel(
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
        mode_sums: wp.array(dtype=modes_sums_vec),
        err_out: wp.array(dtype=wp.float32),
        loglik_out: wp.array(dtype=wp.float32),
        nis_out: wp.array(dtype=wp.float32),
        n_valid_out: wp.array(dtype=wp.int32),
        lam_out: wp.array(dtype=wp.mat33),
        info_out: wp.array(dtype=wp.vec3),
        post_out: wp.array(dtype=modes_vec),
    ):
        """The ray-casting model's reduction, one thread per particle on the CPU: the outputs of
        :data:`warptan.kernels.likelihood.reduce_loglik_kernels` ``[False, modes]``; ``mode_sums`` as in
        :data:`sliding_loglik_simd_kernels`."""
        t = wp.tid()
        b = (row0 + t) // n_per
        mat = quat_to_mat_wxyz(quat_nb[t])
        macc = modes_init()
        if wp.static(with_modes):
            acc = acc_unpack(ray_sums_modes_simd(residual, normal, vertical, mat, cloud, b, t, params, modes,
                                                 mode_sums))
            macc = acc_set_modes(modes_unpack(mode_sums[t]), modes, residual.shape[1], mode_mean[t], mode_var[b])
            post_out[t] = mode_post(macc, modes, residual.shape[1])
        else:
            acc = acc_unpack(ray_sums_simd(residual, normal, vertical, mat, cloud, b, t, params))
        acc_store(t, acc, macc, params, att_cov[b], err_out, loglik_out, nis_out, n_valid_out, lam_out, info_out)

    return reduce_loglik_simd_kernel


sliding_loglik_simd_kernels = {modes: _sliding_simd(modes) for modes in (False, True)}
"""The sliding model's CPU kernels with the points as SIMD lanes, ``[modes]``: with the map-error modes' sums."""
reduce_loglik_simd_kernels = {modes: _reduce_simd(modes) for modes in (False, True)}
"""The ray-casting model's CPU reductions with the points as SIMD lanes, ``[modes]``."""
