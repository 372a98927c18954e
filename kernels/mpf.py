"""Marginalized particle filter kernels (SPEC §6; Schön, Gustafsson & Nordlund 2005; paper §IV).

Particle i holds the position error ``dp_i`` (vec3, m) and the mean ``l_i`` (vec12) of its Kalman filter
over ``[dv, dth, dba, dbg]``; the 12×12 covariance is shared and lives on the host. Weights are kept as
log-weights. Every reduction is done in a fixed order (``N_CHUNKS`` strided partial sums in float64,
then one thread combining them), so that the same seed on the same device gives bit-identical results:
no floating-point atomics.
"""

import warp as wp

from warptan.kernels.frames import quat_exp_wxyz, quat_mul_wxyz

wp.set_module_options({"enable_backward": False})

vec12 = wp.types.vector(length=12, dtype=wp.float32)
mat12 = wp.types.matrix(shape=(12, 12), dtype=wp.float32)
mat3x12 = wp.types.matrix(shape=(3, 12), dtype=wp.float32)
mat12x3 = wp.types.matrix(shape=(12, 3), dtype=wp.float32)

N_CHUNKS = wp.constant(256)
"""Number of partial sums of a reduction (threads of its first stage)."""
N_MOMENTS = wp.constant(1 + 3 + 9 + 12 + 144)
"""Moments reduced for the estimate: Σw, Σw dp, Σw dp dpᵀ, Σw l, Σw l lᵀ."""


@wp.func
def gaussian3(state: wp.uint32) -> wp.vec3:
    """Three independent standard normal numbers."""
    return wp.vec3(wp.randn(state), wp.randn(state), wp.randn(state))


@wp.kernel
def init_particles_kernel(
    seed: int,
    chol_pos: wp.mat33,
    dp_out: wp.array(dtype=wp.vec3),
    lin_out: wp.array(dtype=vec12),
    logw_out: wp.array(dtype=wp.float32),
):
    """dp_i ~ N(0, L Lᵀ), l_i = 0, uniform log-weights."""
    i = wp.tid()
    state = wp.rand_init(seed, i)
    dp_out[i] = chol_pos * gaussian3(state)
    lin_out[i] = vec12()
    logw_out[i] = -wp.log(float(dp_out.shape[0]))


@wp.kernel
def respread_kernel(
    seed: int,
    centre: wp.vec3,
    chol_pos: wp.mat33,
    dp_out: wp.array(dtype=wp.vec3),
    logw_out: wp.array(dtype=wp.float32),
):
    """Re-spread the position errors around ``centre`` with the prior spread; uniform weights (recovery)."""
    i = wp.tid()
    state = wp.rand_init(seed, i)
    dp_out[i] = centre + chol_pos * gaussian3(state)
    logw_out[i] = -wp.log(float(dp_out.shape[0]))


@wp.kernel
def time_update_kernel(
    row0: int,
    seeds: wp.array(dtype=wp.int32),
    a_n: wp.array(dtype=mat3x12),
    a_l: wp.array(dtype=mat12),
    gain: wp.array(dtype=mat12x3),
    chol_n: wp.array(dtype=wp.mat33),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
):
    """K IMU steps of every particle (SPEC §6 steps 3–4), in place; step k uses the k-th matrices:
    ``dp_i += A^n l_i + e_i`` with ``e_i ~ N(0, N_k)``; ``l_i = A^l l_i + L_k e_i``. ``row0`` is the global
    index of this launch's first particle (the random stream of particle i does not depend on chunking)."""
    i = wp.tid()
    d = dp[i]
    lm = lin[i]
    for k in range(seeds.shape[0]):
        state = wp.rand_init(seeds[k], row0 + i)
        e = chol_n[k] * gaussian3(state)
        d = d + a_n[k] * lm + e
        lm = a_l[k] * lm + gain[k] * e
    dp[i] = d
    lin[i] = lm


@wp.kernel
def particle_poses_kernel(
    pos_nom: wp.vec3d,
    quat_nom: wp.vec4,
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
    pos_out: wp.array(dtype=wp.vec3),
    quat_out: wp.array(dtype=wp.vec4),
):
    """Hypothetical poses ``p_i = p_nom + dp_i`` (sum in float64), ``q_i = q_nom ⊗ Exp(dth_i)``."""
    i = wp.tid()
    d = dp[i]
    lm = lin[i]
    pos_out[i] = wp.vec3(
        wp.float32(pos_nom[0] + wp.float64(d[0])),
        wp.float32(pos_nom[1] + wp.float64(d[1])),
        wp.float32(pos_nom[2] + wp.float64(d[2])),
    )
    quat_out[i] = wp.normalize(quat_mul_wxyz(quat_nom, quat_exp_wxyz(wp.vec3(lm[3], lm[4], lm[5]))))


@wp.kernel
def add_loglik_partials_kernel(
    loglik: wp.array(dtype=wp.float32),
    n_valid: wp.array(dtype=wp.int32),
    floor: float,
    logw: wp.array(dtype=wp.float32),
    max_out: wp.array(dtype=wp.float32),
    counts_out: wp.array2d(dtype=wp.int32),
):
    """Stage 1 of the weight update, chunk c: ``logw_i += loglik_i`` (a non-finite loglik counts as bad and
    scores ``floor``), partial maximum, and the chunk's counts [bad logliks, particles with no valid point]."""
    c = wp.tid()
    n = logw.shape[0]
    best = float(-1.0e38)
    bad = int(0)
    unpredictable = int(0)
    i = c
    while i < n:
        if n_valid[i] == 0:
            unpredictable += 1
        ll = loglik[i]
        if not wp.isfinite(ll):
            ll = floor
            bad += 1
        lw = logw[i] + ll
        if not wp.isfinite(lw):
            lw = -1.0e30
        logw[i] = lw
        best = wp.max(best, lw)
        i += N_CHUNKS
    max_out[c] = best
    counts_out[c, 0] = bad
    counts_out[c, 1] = unpredictable


@wp.kernel
def max_of_partials_kernel(max_in: wp.array(dtype=wp.float32), counts_in: wp.array2d(dtype=wp.int32),
                           stats_out: wp.array(dtype=wp.float64)):
    """One thread: stats[3] = max log-weight, stats[2] = bad log-likelihoods, stats[4] = particles that
    could predict no point."""
    m = max_in[0]
    bad = int(0)
    unpredictable = int(0)
    for k in range(N_CHUNKS):
        m = wp.max(m, max_in[k])
        bad += counts_in[k, 0]
        unpredictable += counts_in[k, 1]
    stats_out[2] = wp.float64(bad)
    stats_out[4] = wp.float64(unpredictable)
    stats_out[3] = wp.float64(m)


@wp.kernel
def exp_partials_kernel(
    logw: wp.array(dtype=wp.float32),
    stats: wp.array(dtype=wp.float64),
    sums_out: wp.array2d(dtype=wp.float64),
):
    """Stage 2, chunk c: partial ``Σ exp(lw - max)`` and ``Σ exp(2 (lw - max))``."""
    c = wp.tid()
    m = wp.float32(stats[3])
    n = logw.shape[0]
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    i = c
    while i < n:
        x = wp.float64(wp.exp(logw[i] - m))
        s1 += x
        s2 += x * x
        i += N_CHUNKS
    sums_out[c, 0] = s1
    sums_out[c, 1] = s2


@wp.kernel
def weight_stats_kernel(sums_in: wp.array2d(dtype=wp.float64), stats_out: wp.array(dtype=wp.float64)):
    """One thread: stats[0] = ESS = (Σw)²/Σw², stats[1] = log-normaliser = max + log Σ exp(lw - max)."""
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    for k in range(N_CHUNKS):
        s1 += sums_in[k, 0]
        s2 += sums_in[k, 1]
    stats_out[0] = s1 * s1 / s2
    stats_out[1] = stats_out[3] + wp.log(s1)


@wp.kernel
def normalize_weights_kernel(stats: wp.array(dtype=wp.float64), logw: wp.array(dtype=wp.float32)):
    """``lw_i -= log-normaliser``: the weights sum to one."""
    i = wp.tid()
    logw[i] = wp.float32(wp.float64(logw[i]) - stats[1])


@wp.kernel
def moment_partials_kernel(
    logw: wp.array(dtype=wp.float32),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
    partial_out: wp.array2d(dtype=wp.float64),
):
    """Chunk c: float64 partial sums of w, w dp, w dp dpᵀ, w l, w l lᵀ (weights normalised)."""
    c = wp.tid()
    n = logw.shape[0]
    for k in range(N_MOMENTS):
        partial_out[c, k] = wp.float64(0.0)
    i = c
    while i < n:
        w = wp.float64(wp.exp(logw[i]))
        d = dp[i]
        lm = lin[i]
        partial_out[c, 0] += w
        for a in range(3):
            partial_out[c, 1 + a] += w * wp.float64(d[a])
            for b in range(3):
                partial_out[c, 4 + 3 * a + b] += w * wp.float64(d[a]) * wp.float64(d[b])
        for a in range(12):
            partial_out[c, 13 + a] += w * wp.float64(lm[a])
            for b in range(12):
                partial_out[c, 25 + 12 * a + b] += w * wp.float64(lm[a]) * wp.float64(lm[b])
        i += N_CHUNKS


@wp.kernel
def combine_partials_kernel(partial_in: wp.array2d(dtype=wp.float64), total_out: wp.array(dtype=wp.float64)):
    """One thread per moment: sum the chunks in order."""
    k = wp.tid()
    s = wp.float64(0.0)
    for c in range(partial_in.shape[0]):
        s += partial_in[c, k]
    total_out[k] = s


@wp.kernel
def weights_from_log_kernel(logw: wp.array(dtype=wp.float32), w_out: wp.array(dtype=wp.float32)):
    """``w_i = exp(lw_i)`` (normalised log-weights)."""
    i = wp.tid()
    w_out[i] = wp.exp(logw[i])


@wp.func
def search_cdf(cdf: wp.array(dtype=wp.float32), u: float) -> int:
    """Smallest index with ``cdf[index] > u`` (clamped to the last particle)."""
    lo = int(0)
    hi = cdf.shape[0] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if cdf[mid] > u:
            hi = mid
        else:
            lo = mid + 1
    return lo


@wp.kernel
def ancestors_kernel(
    seed: int,
    scheme: int,
    cdf: wp.array(dtype=wp.float32),
    ancestors_out: wp.array(dtype=wp.int32),
):
    """Ancestor of slot j: 0 systematic ``(j + U)/N`` (one U), 1 stratified ``(j + U_j)/N``, 2 multinomial ``U_j``."""
    j = wp.tid()
    n = cdf.shape[0]
    total = cdf[n - 1]
    u = float(0.0)
    if scheme == 0:
        shared = wp.rand_init(seed, 0)
        u = (float(j) + wp.randf(shared)) / float(n)
    elif scheme == 1:
        own = wp.rand_init(seed, j)
        u = (float(j) + wp.randf(own)) / float(n)
    else:
        own = wp.rand_init(seed, j)
        u = wp.randf(own)
    ancestors_out[j] = search_cdf(cdf, u * total)


@wp.kernel
def gather_kernel(
    ancestors: wp.array(dtype=wp.int32),
    dp_in: wp.array(dtype=wp.vec3),
    lin_in: wp.array(dtype=vec12),
    dp_out: wp.array(dtype=wp.vec3),
    lin_out: wp.array(dtype=vec12),
    logw_out: wp.array(dtype=wp.float32),
):
    """Copy each slot's ancestor; weights become uniform."""
    j = wp.tid()
    a = ancestors[j]
    dp_out[j] = dp_in[a]
    lin_out[j] = lin_in[a]
    logw_out[j] = -wp.log(float(dp_in.shape[0]))

