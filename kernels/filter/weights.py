"""Weights: log-likelihoods applied, the weight statistics (ESS, mean, the regularisation kernel, posterior NIS,
attitude information), normalisation and each particle's Kalman measurement update."""

import warp as wp

from warptan.kernels.block import on_cuda, warp_max, warp_sum
from warptan.kernels.filter.common import (
    FB_CONVERGED,
    JITTER_NIS,
    N_CHUNK_SUMS,
    N_CHUNKS,
    ST_ACTIVE,
    ST_APPLIED,
    ST_BAD,
    ST_CHOL,
    ST_ESS,
    ST_GAMMA,
    ST_INFLATE,
    ST_JITTER,
    ST_LAM,
    ST_LOGNORM,
    ST_MAX,
    ST_MEAN_DP,
    ST_NIS,
    ST_NIS_MIN,
    ST_REMAIN,
    ST_RESAMPLE,
    ST_RESAMPLES,
    ST_SKIP,
    ST_UNPREDICTABLE,
    WARP_LANES,
    UpdateParams,
    chol3,
    chunk_range,
    chunk_sum,
    chunk_vec,
    pair_products,
    stage_loglik,
    vec12,
    weighted_cov,
)
from warptan.kernels.likelihood import META_FLOOR

wp.set_module_options({"enable_backward": False})

@wp.func
def add_loglik_partial(
    b: int,
    c: int,
    n_per: int,
    loglik: wp.array(dtype=wp.float32),
    n_valid: wp.array(dtype=wp.int32),
    meta: wp.array2d(dtype=wp.float32),
    stats: wp.array2d(dtype=wp.float64),
    nis: wp.array(dtype=wp.float32),
    logw: wp.array(dtype=wp.float32),
    max_out: wp.array2d(dtype=wp.float32),
    counts_out: wp.array3d(dtype=wp.int32),
    min_nis_out: wp.array2d(dtype=wp.float32),
):
    """Filter b (active in this stage), chunk c: ``logw_i += γ loglik_i`` (a non-finite loglik counts as bad
    and scores the filter's floor ``meta[b, META_FLOOR]``), partial maximum, the chunk's counts [bad logliks,
    particles with no valid point] and its smallest NIS."""
    if stats[b, ST_ACTIVE] == wp.float64(0.0):
        return
    gamma = wp.float32(stats[b, ST_GAMMA])
    lo, hi = chunk_range(c, n_per)
    best = float(-1.0e38)
    least = float(1.0e38)
    bad = int(0)
    unpredictable = int(0)
    for k in range(lo, hi):
        i = b * n_per + k
        if n_valid[i] == 0:
            unpredictable += 1
        z = nis[i]
        if wp.isfinite(z):
            least = wp.min(least, z)
        if not wp.isfinite(loglik[i]):
            bad += 1
        lw = logw[i] + gamma * stage_loglik(loglik[i], meta[b, META_FLOOR])
        if not wp.isfinite(lw):
            lw = -1.0e30
        logw[i] = lw
        best = wp.max(best, lw)
    max_out[b, c] = best
    counts_out[b, c, 0] = bad
    counts_out[b, c, 1] = unpredictable
    min_nis_out[b, c] = least


@wp.kernel
def add_loglik_partials_kernel(
    n_per: int,
    loglik: wp.array(dtype=wp.float32),
    n_valid: wp.array(dtype=wp.int32),
    meta: wp.array2d(dtype=wp.float32),
    stats: wp.array2d(dtype=wp.float64),
    nis: wp.array(dtype=wp.float32),
    logw: wp.array(dtype=wp.float32),
    max_out: wp.array2d(dtype=wp.float32),
    counts_out: wp.array3d(dtype=wp.int32),
    min_nis_out: wp.array2d(dtype=wp.float32),
):
    """One thread per (b, c): :func:`add_loglik_partial`."""
    b, c = wp.tid()
    add_loglik_partial(b, c, n_per, loglik, n_valid, meta, stats, nis, logw, max_out, counts_out, min_nis_out)



@wp.func
def max_of_partials(b: int, lane: int, max_in: wp.array2d(dtype=wp.float32), counts_in: wp.array3d(dtype=wp.int32),
                    min_nis_in: wp.array2d(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64)):
    """An active filter: the maximum log-weight, bad log-likelihoods, unpredictable particles, the smallest NIS over
    its chunks. On CUDA by the 32 lanes of a warp (every lane calls it: chunks ``lane`` and ``lane + 32``, then the
    warp's butterfly; maxima, minima and whole counts in float64 are exact in any order, the same bits as one thread
    in order, which the CPU runs; lane 0 took 1.2 µs a stage on an H100)."""
    if stats[b, ST_ACTIVE] == wp.float64(0.0):
        return
    m = max_in[b, 0]
    least = min_nis_in[b, 0]
    bad = int(0)
    unpredictable = int(0)
    if on_cuda() == 0:
        for k in range(N_CHUNKS):
            m = wp.max(m, max_in[b, k])
            least = wp.min(least, min_nis_in[b, k])
            bad += counts_in[b, k, 0]
            unpredictable += counts_in[b, k, 1]
    else:
        k = lane + WARP_LANES
        m = wp.float32(warp_max(wp.float64(wp.max(max_in[b, lane], max_in[b, k]))))
        least = wp.float32(-warp_max(-wp.float64(wp.min(min_nis_in[b, lane], min_nis_in[b, k]))))
        bad = int(warp_sum(wp.float64(counts_in[b, lane, 0] + counts_in[b, k, 0])))
        unpredictable = int(warp_sum(wp.float64(counts_in[b, lane, 1] + counts_in[b, k, 1])))
    if lane != 0:
        return
    stats[b, ST_NIS_MIN] = wp.float64(least)
    stats[b, ST_BAD] = wp.float64(bad)
    stats[b, ST_UNPREDICTABLE] = wp.float64(unpredictable)
    stats[b, ST_MAX] = wp.float64(m)


@wp.kernel
def max_of_partials_kernel(max_in: wp.array2d(dtype=wp.float32), counts_in: wp.array3d(dtype=wp.int32),
                           min_nis_in: wp.array2d(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64)):
    """Filter b, a warp (``wp.launch_tiled``, ``WARP_LANES`` lanes; one thread on the CPU): :func:`max_of_partials`."""
    b, lane = wp.tid()
    max_of_partials(b, lane, max_in, counts_in, min_nis_in, stats)


@wp.func
def exp_partial(
    b: int,
    c: int,
    n_per: int,
    logw: wp.array(dtype=wp.float32),
    dp: wp.array(dtype=wp.vec3),
    nis: wp.array(dtype=wp.float32),
    lam: wp.array(dtype=wp.mat33),
    with_ip: int,
    info_pos: wp.array(dtype=wp.vec3),
    stats: wp.array2d(dtype=wp.float64),
    sums_out: wp.array3d(dtype=wp.float64),
):
    """Active filter b, chunk c, with ``e_i = exp(lw_i - max)``: partial ``Σe``, ``Σe²``, ``Σe dp``, ``Σe dp dpᵀ``,
    ``Σe nis``, ``Σe Λ`` and ``Σe I_p`` (``N_CHUNK_SUMS`` values; ``with_ip`` 0: no position information, zeros)."""
    if stats[b, ST_ACTIVE] == wp.float64(0.0):
        return
    lo, hi = chunk_range(c, n_per)
    m = wp.float32(stats[b, ST_MAX])
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    sz = wp.float64(0.0)
    m1 = wp.vec3d()
    m2 = wp.vec3d()
    m3 = wp.vec3d()
    ld = wp.vec3d()
    lo_ = wp.vec3d()
    ip = wp.vec3d()
    for k in range(lo, hi):
        i = b * n_per + k
        x = wp.float64(wp.exp(logw[i] - m))
        d = wp.vec3d(dp[i])
        li = wp.mat33d(lam[i])
        ld += x * wp.vec3d(li[0, 0], li[1, 1], li[2, 2])
        lo_ += x * wp.vec3d(li[0, 1], li[0, 2], li[1, 2])
        s1 += x
        s2 += x * x
        m1 += x * d
        m2 += x * wp.cw_mul(d, d)
        m3 += x * pair_products(d)
        z = nis[i]
        if wp.isfinite(z):
            sz += x * wp.float64(z)
        if with_ip != 0:
            ip += x * wp.vec3d(info_pos[i])
    sums_out[b, c, 0] = s1
    sums_out[b, c, 1] = s2
    for a in range(3):
        sums_out[b, c, 2 + a] = m1[a]
        sums_out[b, c, 5 + a] = m2[a]
        sums_out[b, c, 8 + a] = m3[a]
        sums_out[b, c, 12 + a] = ld[a]
        sums_out[b, c, 15 + a] = lo_[a]
        sums_out[b, c, 18 + a] = ip[a]
    sums_out[b, c, 11] = sz


@wp.kernel
def exp_partials_kernel(
    n_per: int,
    logw: wp.array(dtype=wp.float32),
    dp: wp.array(dtype=wp.vec3),
    nis: wp.array(dtype=wp.float32),
    lam: wp.array(dtype=wp.mat33),
    with_ip: int,
    info_pos: wp.array(dtype=wp.vec3),
    stats: wp.array2d(dtype=wp.float64),
    sums_out: wp.array3d(dtype=wp.float64),
):
    """One thread per (b, c): :func:`exp_partial`."""
    b, c = wp.tid()
    exp_partial(b, c, n_per, logw, dp, nis, lam, with_ip, info_pos, stats, sums_out)


@wp.func
def weight_stats(
    b: int,
    lane: int,
    n_per: int,
    params: UpdateParams,
    sums_in: wp.array3d(dtype=wp.float64),
    stats: wp.array2d(dtype=wp.float64),
    kernel_chol: wp.array(dtype=wp.mat33),
):
    """One block per active filter (``wp.launch_tiled``, lanes over the chunks): ESS = (Σw)²/Σw², log-normaliser,
    weighted mean and Cholesky factor of the covariance of dp (the regularisation kernel's shape), posterior NIS,
    weighted mean Λ̄, the bandwidth's factor ``ST_JITTER`` (:data:`JITTER_NIS`; 1 without position information) and
    the kernel factor ``kernel_chol[b] = h · ST_JITTER · chol(Σ̂)`` the altimeter scores with, the share
    ``ST_INFLATE`` of the shrinkage's covariance growth ``g = (1 − s) h²`` the resampling keeps, and the decision to
    resample: when ESS < threshold · n, or when exponent remains (between tempering stages).

    ``ST_INFLATE`` is 1 unless the growth would take the cloud's horizontal variance ``tr Σ̂`` past the unaided INS's
    ``params.free_var[b]`` (:meth:`warptan.filter.mpf.MarginalizedParticleFilter._unaided_terms`, plus one prior of
    margin for the acquisition, ``CAP_MARGIN``), then ``(free − tr Σ̂) / (g tr Σ̂)`` clipped to [0, 1]: the growth is a
    forgetting of what the map taught, and forgetting it cannot make the position less known than the INS alone knows
    it. A cloud that no reading narrows (an altimeter over flat ground with a map error: S12) otherwise grows by ``1 +
    g`` at each resampling without end, and its mean follows the map error's spurious slopes: S12 over a 10 m / 3 km
    biased world (20 seeds, 120 s) was 852 m off against the INS's own 163 m, and 187 m with the cap (without the
    margin), 3σ coverage 83/94 → 97/98 %. A cloud a scan narrows is far inside it (S8 and S5 gave the same bits)."""
    if stats[b, ST_ACTIVE] == wp.float64(0.0):
        return
    # what lane 0 reads of the statistics, read before it writes any (a load after a store waits for it: on an H100
    # each such round trip cost ~0.4 µs of this piece's 7)
    max_lw = stats[b, ST_MAX]
    remain = stats[b, ST_REMAIN]
    resamples = stats[b, ST_RESAMPLES]
    tot = chunk_vec()
    if lane < WARP_LANES:  # (the block's first warp; the CPU's one thread)
        for a in range(N_CHUNK_SUMS):
            tot[a] = chunk_sum(b, lane, a, sums_in)
    if lane != 0:
        return
    s1 = tot[0]
    inv = wp.float64(1.0) / s1  # (one division: a float64 division is a chain of its own on CUDA)
    ess = s1 * s1 / tot[1]
    stats[b, ST_ESS] = ess
    stats[b, ST_LOGNORM] = max_lw + wp.log(s1)
    m1 = wp.vec3d(tot[2], tot[3], tot[4])
    for a in range(3):
        stats[b, ST_MEAN_DP + a] = m1[a] * inv
    cov = weighted_cov(inv, m1, wp.vec3d(tot[5], tot[6], tot[7]), wp.vec3d(tot[8], tot[9], tot[10]))
    lo = chol3(cov + wp.float64(1.0e-6) * wp.identity(n=3, dtype=wp.float64))
    stats[b, ST_CHOL + 0] = lo[0, 0]
    stats[b, ST_CHOL + 1] = lo[1, 0]
    stats[b, ST_CHOL + 2] = lo[1, 1]
    stats[b, ST_CHOL + 3] = lo[2, 0]
    stats[b, ST_CHOL + 4] = lo[2, 1]
    stats[b, ST_CHOL + 5] = lo[2, 2]
    stats[b, ST_NIS] = tot[11] * inv
    # JITTER_NIS: tr(h² Σ̂ Ī_p) with Σ̂ = L Lᵀ (its horizontal block)
    ip = wp.vec3d(tot[18], tot[19], tot[20]) * inv
    q = wp.float64(params.bandwidth * params.bandwidth) * (cov[0, 0] * ip[0] + cov[1, 1] * ip[1]
                                                           + wp.float64(2.0) * cov[0, 1] * ip[2])
    jitter = wp.float64(1.0)
    if q > wp.float64(JITTER_NIS):
        jitter = wp.sqrt(wp.float64(JITTER_NIS) / q)
    stats[b, ST_JITTER] = jitter
    # INFLATE: the shrinkage's growth stops at the unaided INS's horizontal variance (free_var)
    grow = wp.float64(1.0 - params.shrinkage) * wp.float64(params.bandwidth * params.bandwidth) * jitter * jitter
    tr = cov[0, 0] + cov[1, 1]
    cap = wp.float64(params.free_var[b])
    inflate = wp.float64(1.0)
    if grow > wp.float64(0.0) and tr * (wp.float64(1.0) + grow) > cap:
        inflate = wp.max(wp.min((cap - tr) / (grow * tr), wp.float64(1.0)), wp.float64(0.0))
    stats[b, ST_INFLATE] = inflate
    z = wp.float32(0.0)  # (stats_chol of what was just stored)
    kernel_chol[b] = wp.float32(wp.float64(params.bandwidth) * jitter) * wp.mat33(
        wp.float32(lo[0, 0]), z, z, wp.float32(lo[1, 0]), wp.float32(lo[1, 1]), z,
        wp.float32(lo[2, 0]), wp.float32(lo[2, 1]), wp.float32(lo[2, 2]))
    for a in range(6):
        stats[b, ST_LAM + a] = tot[12 + a] * inv
    if ess < wp.float64(params.resample_threshold) * wp.float64(n_per) or remain > wp.float64(0.0):
        stats[b, ST_RESAMPLE] = wp.float64(1.0)
        stats[b, ST_RESAMPLES] = resamples + wp.float64(1.0)


@wp.kernel
def weight_stats_kernel(
    n_per: int,
    params: UpdateParams,
    sums_in: wp.array3d(dtype=wp.float64),
    stats: wp.array2d(dtype=wp.float64),
    kernel_chol: wp.array(dtype=wp.mat33),
):
    """One thread per (b, lane): :func:`weight_stats`."""
    b, lane = wp.tid()
    weight_stats(b, lane, n_per, params, sums_in, stats, kernel_chol)



@wp.func
def normalize_weight(i: int, n_per: int, stats: wp.array2d(dtype=wp.float64), logw: wp.array(dtype=wp.float32)):
    """``lw_i -= log-normaliser`` in the active filters: the weights of each filter sum to one."""
    b = i // n_per
    if stats[b, ST_ACTIVE] != wp.float64(0.0):
        logw[i] = wp.float32(wp.float64(logw[i]) - stats[b, ST_LOGNORM])


@wp.kernel
def normalize_weights_kernel(n_per: int, stats: wp.array2d(dtype=wp.float64), logw: wp.array(dtype=wp.float32)):
    """One thread per (i): :func:`normalize_weight`."""
    i = wp.tid()
    normalize_weight(i, n_per, stats, logw)


@wp.func
def kalman_update(
    i: int,
    n_per: int,
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    feedback: wp.array2d(dtype=wp.float64),
    p_col: wp.array2d(dtype=wp.mat33),
    lam: wp.array(dtype=wp.mat33),
    info: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
):
    """The Kalman measurement update of each particle's linear states (design notes §6b), in the stage that applies the
    last of the filter's exponent (not in a skipped update): with the shared prior ``P``, ``A = P_θθ`` and the
    particle's own attitude information ``Λ_i``, ``b_i`` (its residuals at its own pose, scaled by the exponent
    applied), ``l_i += P_:θ (I + Λ_i A)⁻¹ b_i`` — 3×3 work per particle whatever the number of points.
    ``p_col[b, r]`` is the block ``P_rθ`` of filter b (r = dv, dθ, dba, dbg). With ``params.gate_linear`` only in a
    filter whose integrity monitor judged it consistent at the previous update (FB_CONVERGED)."""
    b = i // n_per
    if stats[b, ST_ACTIVE] == wp.float64(0.0) or stats[b, ST_REMAIN] > wp.float64(0.0):
        return
    if params.gate_linear != 0 and feedback[b, FB_CONVERGED] == wp.float64(0.0):
        return
    if stats[b, ST_SKIP] != wp.float64(0.0):
        return
    scale = stats[b, ST_APPLIED]
    a = wp.mat33d(p_col[b, 1])
    m = wp.identity(n=3, dtype=wp.float64) + scale * wp.mat33d(lam[i]) * a
    det = wp.determinant(m)
    if not (det > wp.float64(0.0)):
        return
    x = wp.vec3(wp.inverse(m) * (scale * wp.vec3d(info[i])))
    if not (wp.isfinite(x[0]) and wp.isfinite(x[1]) and wp.isfinite(x[2])):
        return
    d0 = p_col[b, 0] * x
    d1 = p_col[b, 1] * x
    d2 = p_col[b, 2] * x
    d3 = p_col[b, 3] * x
    lin[i] = lin[i] + vec12(d0[0], d0[1], d0[2], d1[0], d1[1], d1[2], d2[0], d2[1], d2[2], d3[0], d3[1], d3[2])


@wp.kernel
def kalman_update_kernel(
    n_per: int,
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    feedback: wp.array2d(dtype=wp.float64),
    p_col: wp.array2d(dtype=wp.mat33),
    lam: wp.array(dtype=wp.mat33),
    info: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
):
    """One thread per (i): :func:`kalman_update`."""
    i = wp.tid()
    kalman_update(i, n_per, params, stats, feedback, p_col, lam, info, lin)
