"""Marginalized particle filter kernels (SPEC §6; Schön, Gustafsson & Nordlund 2005; paper §IV).

Particle i holds the position error ``dp_i`` (vec3, m) and the mean ``l_i`` (vec12) of its Kalman filter
over ``[dv, dth, dba, dbg]``; the 12×12 covariance is shared and lives on the host. Weights are kept as
log-weights.

A batch of B independent filters of n particles each is one array of N = B·n particles, filter-major:
particle i belongs to filter ``b = i // n``. Per-filter values (statistics, decisions) are (B, k) arrays.

Every reduction runs in a fixed order (``N_CHUNKS`` contiguous partial sums per filter in float64, then one
thread per filter combining them), so that the same seed on the same device gives bit-identical results:
no floating-point atomics. Decisions that used to need the host — re-spread a lost filter, resample — are
flags in ``stats`` that the later kernels read, so a whole measurement update runs with no host sync and
can be captured in a graph.
"""

import warp as wp

from warptan.kernels.frames import quat_exp_wxyz, quat_mul_wxyz

wp.set_module_options({"enable_backward": False})

vec12 = wp.types.vector(length=12, dtype=wp.float32)
vec10d = wp.types.vector(length=10, dtype=wp.float64)

N_CHUNKS = wp.constant(64)
"""Partial sums per filter in the weight reductions (threads of their first stage, per filter)."""
N_MOMENT_CHUNKS = wp.constant(16)
"""Partial sums per filter of the moments of the estimate."""
N_MOMENTS = wp.constant(1 + 3 + 9 + 12 + 144)
"""Moments reduced for the estimate: Σw, Σw dp, Σw dp dpᵀ, Σw l, Σw l lᵀ."""
N_STATS = wp.constant(12)
"""Per-filter statistics of an update (columns of ``stats``, ``ST_*``)."""
ST_ESS = wp.constant(0)
ST_LOGNORM = wp.constant(1)
ST_BAD = wp.constant(2)
ST_MAX = wp.constant(3)
ST_UNPREDICTABLE = wp.constant(4)
ST_MEAN_DP = wp.constant(5)  # 3 values: the weighted mean of dp (before resampling)
ST_RESPREAD = wp.constant(8)
ST_RESAMPLE = wp.constant(9)
N_SUMMARY = wp.constant(16)
"""Per-filter record of an update: ESS, resampled, respread, bad, unpredictable, Σw, mean dp (3),
covariance of dp (xx, yy, zz, xy, xz, yz), 0."""


@wp.func
def chunk_range(c: int, n: int):
    """Particles ``[lo, hi)`` (within a filter of n) of chunk c."""
    size = (n + N_CHUNKS - 1) // N_CHUNKS
    lo = wp.min(c * size, n)
    return lo, wp.min(lo + size, n)


@wp.func
def gaussian3(state: wp.uint32) -> wp.vec3:
    """Three independent standard normal numbers."""
    return wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))


@wp.func
def gaussian_blocks(state: wp.uint32):
    """Five independent standard normal vec3 (one state: the draws must share it)."""
    z0 = wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))
    z1 = wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))
    z2 = wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))
    z3 = wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))
    z4 = wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))
    return z0, z1, z2, z3, z4


@wp.kernel
def init_particles_kernel(
    n_per: int,
    seeds: wp.array(dtype=wp.int32),
    chol_pos: wp.mat33,
    dp_out: wp.array(dtype=wp.vec3),
    lin_out: wp.array(dtype=vec12),
    logw_out: wp.array(dtype=wp.float32),
):
    """dp_i ~ N(0, L Lᵀ), l_i = 0, uniform log-weights (stream: the filter's seed, the particle's index)."""
    i = wp.tid()
    state = wp.rand_init(seeds[i // n_per], i % n_per)
    dp_out[i] = chol_pos * gaussian3(state)
    lin_out[i] = vec12()
    logw_out[i] = -wp.log(float(n_per))


@wp.kernel
def time_update_kernel(
    row0: int,
    n_per: int,
    seeds: wp.array(dtype=wp.int32),
    phi: wp.array3d(dtype=wp.mat33),
    chol: wp.array3d(dtype=wp.mat33),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
):
    """One measurement interval of every particle (SPEC §6 steps 3–4 over its K IMU steps, composed by
    :mod:`warptan.kernels.nav`): ``x = [dp, l] <- Φ x + C z``, ``z ~ N(0, I15)``, in 3×3 blocks.
    ``row0`` is the global index of this launch's first particle (the random stream does not depend on
    chunking)."""
    t = wp.tid()
    g = row0 + t
    b = g // n_per
    state = wp.rand_init(seeds[b], g % n_per)
    d = dp[t]
    lm = lin[t]
    x1 = wp.vec3(lm[0], lm[1], lm[2])
    x2 = wp.vec3(lm[3], lm[4], lm[5])
    x3 = wp.vec3(lm[6], lm[7], lm[8])
    x4 = wp.vec3(lm[9], lm[10], lm[11])
    z0, z1, z2, z3, z4 = gaussian_blocks(state)
    y0 = phi[b, 0, 0] * d + phi[b, 0, 1] * x1 + phi[b, 0, 2] * x2 + phi[b, 0, 3] * x3 + phi[b, 0, 4] * x4
    y1 = phi[b, 1, 0] * d + phi[b, 1, 1] * x1 + phi[b, 1, 2] * x2 + phi[b, 1, 3] * x3 + phi[b, 1, 4] * x4
    y2 = phi[b, 2, 0] * d + phi[b, 2, 1] * x1 + phi[b, 2, 2] * x2 + phi[b, 2, 3] * x3 + phi[b, 2, 4] * x4
    y0 += chol[b, 0, 0] * z0
    y1 += chol[b, 1, 0] * z0 + chol[b, 1, 1] * z1
    y2 += chol[b, 2, 0] * z0 + chol[b, 2, 1] * z1 + chol[b, 2, 2] * z2
    y3 = x3 + chol[b, 3, 0] * z0 + chol[b, 3, 1] * z1 + chol[b, 3, 2] * z2 + chol[b, 3, 3] * z3
    y4 = x4 + chol[b, 4, 0] * z0 + chol[b, 4, 1] * z1 + chol[b, 4, 2] * z2 + chol[b, 4, 3] * z3 + chol[b, 4, 4] * z4
    dp[t] = y0
    lin[t] = vec12(y1[0], y1[1], y1[2], y2[0], y2[1], y2[2], y3[0], y3[1], y3[2], y4[0], y4[1], y4[2])


@wp.kernel
def particle_poses_kernel(
    n_per: int,
    pose: wp.array2d(dtype=wp.float64),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
    pos_out: wp.array(dtype=wp.vec3),
    quat_out: wp.array(dtype=wp.vec4),
):
    """Hypothetical poses ``p_i = p_nom + dp_i`` (sum in float64), ``q_i = q_nom ⊗ Exp(dth_i)``;
    ``pose[b] = [p_nom (3), q_nom (4)]`` of the particle's filter."""
    i = wp.tid()
    b = i // n_per
    d = dp[i]
    lm = lin[i]
    pos_out[i] = wp.vec3(
        wp.float32(pose[b, 0] + wp.float64(d[0])),
        wp.float32(pose[b, 1] + wp.float64(d[1])),
        wp.float32(pose[b, 2] + wp.float64(d[2])),
    )
    q_nom = wp.vec4(wp.float32(pose[b, 3]), wp.float32(pose[b, 4]), wp.float32(pose[b, 5]), wp.float32(pose[b, 6]))
    quat_out[i] = wp.normalize(quat_mul_wxyz(q_nom, quat_exp_wxyz(wp.vec3(lm[3], lm[4], lm[5]))))


@wp.kernel
def add_loglik_partials_kernel(
    n_per: int,
    loglik: wp.array(dtype=wp.float32),
    n_valid: wp.array(dtype=wp.int32),
    meta: wp.array2d(dtype=wp.float32),
    logw: wp.array(dtype=wp.float32),
    max_out: wp.array2d(dtype=wp.float32),
    counts_out: wp.array3d(dtype=wp.int32),
):
    """Stage 1 of the weight update, filter b, chunk c: ``logw_i += loglik_i`` (a non-finite loglik counts as
    bad and scores the filter's floor ``meta[b, 1]``), partial maximum, and the chunk's counts [bad logliks,
    particles with no valid point]."""
    b, c = wp.tid()
    lo, hi = chunk_range(c, n_per)
    best = float(-1.0e38)
    bad = int(0)
    unpredictable = int(0)
    for k in range(lo, hi):
        i = b * n_per + k
        if n_valid[i] == 0:
            unpredictable += 1
        ll = loglik[i]
        if not wp.isfinite(ll):
            ll = meta[b, 1]
            bad += 1
        lw = logw[i] + ll
        if not wp.isfinite(lw):
            lw = -1.0e30
        logw[i] = lw
        best = wp.max(best, lw)
    max_out[b, c] = best
    counts_out[b, c, 0] = bad
    counts_out[b, c, 1] = unpredictable


@wp.kernel
def max_of_partials_kernel(max_in: wp.array2d(dtype=wp.float32), counts_in: wp.array3d(dtype=wp.int32),
                           stats_out: wp.array2d(dtype=wp.float64)):
    """One thread per filter: the maximum log-weight, bad log-likelihoods, unpredictable particles."""
    b = wp.tid()
    m = max_in[b, 0]
    bad = int(0)
    unpredictable = int(0)
    for k in range(N_CHUNKS):
        m = wp.max(m, max_in[b, k])
        bad += counts_in[b, k, 0]
        unpredictable += counts_in[b, k, 1]
    stats_out[b, ST_BAD] = wp.float64(bad)
    stats_out[b, ST_UNPREDICTABLE] = wp.float64(unpredictable)
    stats_out[b, ST_MAX] = wp.float64(m)


@wp.kernel
def exp_partials_kernel(
    n_per: int,
    logw: wp.array(dtype=wp.float32),
    dp: wp.array(dtype=wp.vec3),
    stats: wp.array2d(dtype=wp.float64),
    sums_out: wp.array3d(dtype=wp.float64),
):
    """Stage 2, filter b, chunk c: partial ``Σ e_i``, ``Σ e_i²`` and ``Σ e_i dp_i`` with ``e_i = exp(lw_i - max)``."""
    b, c = wp.tid()
    lo, hi = chunk_range(c, n_per)
    m = wp.float32(stats[b, ST_MAX])
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    sd = wp.vec3d()
    for k in range(lo, hi):
        i = b * n_per + k
        x = wp.float64(wp.exp(logw[i] - m))
        s1 += x
        s2 += x * x
        sd += x * wp.vec3d(dp[i])
    sums_out[b, c, 0] = s1
    sums_out[b, c, 1] = s2
    sums_out[b, c, 2] = sd[0]
    sums_out[b, c, 3] = sd[1]
    sums_out[b, c, 4] = sd[2]


@wp.kernel
def weight_stats_kernel(
    n_per: int,
    threshold: float,
    sums_in: wp.array3d(dtype=wp.float64),
    meta: wp.array2d(dtype=wp.float32),
    stats_out: wp.array2d(dtype=wp.float64),
):
    """One thread per filter: ESS = (Σw)²/Σw², log-normaliser, mean dp, and the decisions: re-spread when
    every particle was unpredictable for a measurement with valid points, else resample when
    ESS < threshold · n."""
    b = wp.tid()
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    sd = wp.vec3d()
    for k in range(N_CHUNKS):
        s1 += sums_in[b, k, 0]
        s2 += sums_in[b, k, 1]
        sd += wp.vec3d(sums_in[b, k, 2], sums_in[b, k, 3], sums_in[b, k, 4])
    ess = s1 * s1 / s2
    stats_out[b, ST_ESS] = ess
    stats_out[b, ST_LOGNORM] = stats_out[b, ST_MAX] + wp.log(s1)
    for a in range(3):
        stats_out[b, ST_MEAN_DP + a] = sd[a] / s1
    respread = meta[b, 0] > 0.0 and stats_out[b, ST_UNPREDICTABLE] == wp.float64(n_per)
    stats_out[b, ST_RESPREAD] = wp.float64(0.0)
    stats_out[b, ST_RESAMPLE] = wp.float64(0.0)
    if respread:
        stats_out[b, ST_RESPREAD] = wp.float64(1.0)
    elif ess < wp.float64(threshold) * wp.float64(n_per):
        stats_out[b, ST_RESAMPLE] = wp.float64(1.0)


@wp.kernel
def normalize_weights_kernel(n_per: int, stats: wp.array2d(dtype=wp.float64), logw: wp.array(dtype=wp.float32)):
    """``lw_i -= log-normaliser``: the weights of each filter sum to one."""
    i = wp.tid()
    logw[i] = wp.float32(wp.float64(logw[i]) - stats[i // n_per, ST_LOGNORM])


@wp.kernel
def cdf_partials_kernel(n_per: int, logw: wp.array(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64),
                        sums_out: wp.array2d(dtype=wp.float64)):
    """Filter b (resampling only), chunk c: ``Σ w_i`` over the chunk."""
    b, c = wp.tid()
    if stats[b, ST_RESAMPLE] == wp.float64(0.0):
        return
    lo, hi = chunk_range(c, n_per)
    s = wp.float64(0.0)
    for k in range(lo, hi):
        s += wp.float64(wp.exp(logw[b * n_per + k]))
    sums_out[b, c] = s


@wp.kernel
def cdf_kernel(n_per: int, logw: wp.array(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64),
               sums_in: wp.array2d(dtype=wp.float64), cdf_out: wp.array(dtype=wp.float32)):
    """Filter b (resampling only), chunk c: the inclusive cumulative weights of its particles (float64 sums)."""
    b, c = wp.tid()
    if stats[b, ST_RESAMPLE] == wp.float64(0.0):
        return
    lo, hi = chunk_range(c, n_per)
    s = wp.float64(0.0)
    for k in range(c):
        s += sums_in[b, k]
    for k in range(lo, hi):
        s += wp.float64(wp.exp(logw[b * n_per + k]))
        cdf_out[b * n_per + k] = wp.float32(s)


@wp.func
def search_cdf(cdf: wp.array(dtype=wp.float32), lo_in: int, hi_in: int, u: float) -> int:
    """Smallest index in ``[lo, hi)`` with ``cdf[index] > u`` (clamped to the last one)."""
    lo = lo_in
    hi = hi_in - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if cdf[mid] > u:
            hi = mid
        else:
            lo = mid + 1
    return lo


@wp.kernel
def ancestors_kernel(
    n_per: int,
    seeds: wp.array(dtype=wp.int32),
    scheme: int,
    stats: wp.array2d(dtype=wp.float64),
    cdf: wp.array(dtype=wp.float32),
    ancestors_out: wp.array(dtype=wp.int32),
):
    """Ancestor of slot j of a resampling filter: 0 systematic ``(j + U)/n`` (one U), 1 stratified
    ``(j + U_j)/n``, 2 multinomial ``U_j``; a filter that does not resample keeps its particles."""
    i = wp.tid()
    b = i // n_per
    j = i % n_per
    if stats[b, ST_RESAMPLE] == wp.float64(0.0):
        ancestors_out[i] = i
        return
    lo = b * n_per
    total = cdf[lo + n_per - 1]
    u = float(0.0)
    if scheme == 0:
        shared = wp.rand_init(seeds[b], 0)
        u = (float(j) + wp.randf(shared)) / float(n_per)
    elif scheme == 1:
        own = wp.rand_init(seeds[b], j)
        u = (float(j) + wp.randf(own)) / float(n_per)
    else:
        own = wp.rand_init(seeds[b], j)
        u = wp.randf(own)
    ancestors_out[i] = search_cdf(cdf, lo, lo + n_per, u * total)


@wp.kernel
def gather_kernel(
    n_per: int,
    seeds: wp.array(dtype=wp.int32),
    chol_pos: wp.mat33,
    stats: wp.array2d(dtype=wp.float64),
    ancestors: wp.array(dtype=wp.int32),
    dp_in: wp.array(dtype=wp.vec3),
    lin_in: wp.array(dtype=vec12),
    logw_in: wp.array(dtype=wp.float32),
    dp_out: wp.array(dtype=wp.vec3),
    lin_out: wp.array(dtype=vec12),
    logw_out: wp.array(dtype=wp.float32),
):
    """Slot i takes its ancestor (uniform weights) in a resampling filter; a lost filter re-spreads dp around
    its mean with the prior spread (uniform weights); other filters copy their particles."""
    i = wp.tid()
    b = i // n_per
    a = ancestors[i]
    dp_out[i] = dp_in[a]
    lin_out[i] = lin_in[a]
    logw_out[i] = logw_in[a]
    if stats[b, ST_RESAMPLE] != wp.float64(0.0):
        logw_out[i] = -wp.log(float(n_per))
    if stats[b, ST_RESPREAD] != wp.float64(0.0):
        state = wp.rand_init(seeds[b], i % n_per)
        centre = wp.vec3(wp.float32(stats[b, ST_MEAN_DP]), wp.float32(stats[b, ST_MEAN_DP + 1]),
                         wp.float32(stats[b, ST_MEAN_DP + 2]))
        dp_out[i] = centre + chol_pos * gaussian3(state)
        logw_out[i] = -wp.log(float(n_per))


@wp.kernel
def copy_particles_kernel(dp_in: wp.array(dtype=wp.vec3), lin_in: wp.array(dtype=vec12),
                          logw_in: wp.array(dtype=wp.float32), dp_out: wp.array(dtype=wp.vec3),
                          lin_out: wp.array(dtype=vec12), logw_out: wp.array(dtype=wp.float32)):
    i = wp.tid()
    dp_out[i] = dp_in[i]
    lin_out[i] = lin_in[i]
    logw_out[i] = logw_in[i]


@wp.kernel
def summary_partials_kernel(n_per: int, logw: wp.array(dtype=wp.float32), dp: wp.array(dtype=wp.vec3),
                            partial_out: wp.array3d(dtype=wp.float64)):
    """Filter b, chunk c: Σw, Σw dp (3), Σw dp dpᵀ (xx, yy, zz, xy, xz, yz) after the update."""
    b, c = wp.tid()
    lo, hi = chunk_range(c, n_per)
    s = wp.float64(0.0)
    m1 = wp.vec3d()
    m2 = wp.vec3d()
    m3 = wp.vec3d()
    for k in range(lo, hi):
        i = b * n_per + k
        w = wp.float64(wp.exp(logw[i]))
        d = wp.vec3d(dp[i])
        s += w
        m1 += w * d
        m2 += w * wp.cw_mul(d, d)
        m3 += w * wp.vec3d(d[0] * d[1], d[0] * d[2], d[1] * d[2])
    partial_out[b, c, 0] = s
    for a in range(3):
        partial_out[b, c, 1 + a] = m1[a]
        partial_out[b, c, 4 + a] = m2[a]
        partial_out[b, c, 7 + a] = m3[a]


@wp.kernel
def summary_kernel(partial_in: wp.array3d(dtype=wp.float64), stats: wp.array2d(dtype=wp.float64),
                   slot: wp.array(dtype=wp.int32), history: wp.array3d(dtype=wp.float64)):
    """One thread per filter: the update's record in ``history[slot[0], b]`` (``N_SUMMARY`` values)."""
    b = wp.tid()
    t = slot[0]
    if t >= history.shape[0]:
        return
    tot = vec10d()
    for c in range(N_CHUNKS):
        for a in range(10):
            tot[a] += partial_in[b, c, a]
    s = tot[0]
    mean = wp.vec3d(tot[1], tot[2], tot[3]) / s
    history[t, b, 0] = stats[b, ST_ESS]
    history[t, b, 1] = stats[b, ST_RESAMPLE]
    history[t, b, 2] = stats[b, ST_RESPREAD]
    history[t, b, 3] = stats[b, ST_BAD]
    history[t, b, 4] = stats[b, ST_UNPREDICTABLE]
    history[t, b, 5] = s
    for a in range(3):
        history[t, b, 6 + a] = mean[a]
        history[t, b, 9 + a] = tot[4 + a] / s - mean[a] * mean[a]
    history[t, b, 12] = tot[7] / s - mean[0] * mean[1]
    history[t, b, 13] = tot[8] / s - mean[0] * mean[2]
    history[t, b, 14] = tot[9] / s - mean[1] * mean[2]
    history[t, b, 15] = wp.float64(0.0)


@wp.kernel
def advance_slot_kernel(slot: wp.array(dtype=wp.int32)):
    slot[0] = slot[0] + 1


@wp.kernel
def moment_partials_kernel(
    n_per: int,
    logw: wp.array(dtype=wp.float32),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
    partial_out: wp.array3d(dtype=wp.float64),
):
    """Filter b, chunk c: float64 partial sums of w, w dp, w dp dpᵀ, w l, w l lᵀ (weights normalised)."""
    b, c = wp.tid()
    size = (n_per + N_MOMENT_CHUNKS - 1) // N_MOMENT_CHUNKS
    lo = wp.min(c * size, n_per)
    hi = wp.min(lo + size, n_per)
    for k in range(N_MOMENTS):
        partial_out[b, c, k] = wp.float64(0.0)
    for k in range(lo, hi):
        i = b * n_per + k
        w = wp.float64(wp.exp(logw[i]))
        d = dp[i]
        lm = lin[i]
        partial_out[b, c, 0] += w
        for a in range(3):
            partial_out[b, c, 1 + a] += w * wp.float64(d[a])
            for e in range(3):
                partial_out[b, c, 4 + 3 * a + e] += w * wp.float64(d[a]) * wp.float64(d[e])
        for a in range(12):
            partial_out[b, c, 13 + a] += w * wp.float64(lm[a])
            for e in range(12):
                partial_out[b, c, 25 + 12 * a + e] += w * wp.float64(lm[a]) * wp.float64(lm[e])


@wp.kernel
def combine_partials_kernel(partial_in: wp.array3d(dtype=wp.float64), total_out: wp.array2d(dtype=wp.float64)):
    """One thread per (filter, moment): sum the chunks in order."""
    b, k = wp.tid()
    s = wp.float64(0.0)
    for c in range(partial_in.shape[1]):
        s += partial_in[b, c, k]
    total_out[b, k] = s
