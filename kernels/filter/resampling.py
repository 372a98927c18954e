"""Resampling: cumulative weights, ancestors (systematic, stratified, multinomial), the regularised gather with kernel
shrinkage, and the map-error modes' state."""

import warp as wp

from warptan.kernels.filter.common import (
    ST_INFLATE,
    ST_JITTER,
    ST_MEAN_DP,
    ST_REMAIN,
    ST_RESAMPLE,
    ST_RESPREAD,
    ST_SKIP,
    UpdateParams,
    chunk_range,
    gaussian3,
    search_cdf,
    stats_chol,
    vec12,
)
from warptan.kernels.frames import quat_to_mat_wxyz
from warptan.kernels.likelihood import (
    MAX_MODES,
    MODE_K0,
    MODE_RHO,
    cloud_row,
    mode_prior,
    modes_vec,
    ray_nominal_gain,
    row_dir,
)

wp.set_module_options({"enable_backward": False})

@wp.func
def cdf_partial(b: int, c: int, n_per: int, logw: wp.array(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64),
                sums_out: wp.array2d(dtype=wp.float64)):
    """Filter b (resampling only), chunk c: ``Σ w_i`` over the chunk."""
    if stats[b, ST_RESAMPLE] == wp.float64(0.0):
        return
    lo, hi = chunk_range(c, n_per)
    s = wp.float64(0.0)
    for k in range(lo, hi):
        s += wp.float64(wp.exp(logw[b * n_per + k]))
    sums_out[b, c] = s


@wp.kernel
def cdf_partials_kernel(n_per: int, logw: wp.array(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64),
                        sums_out: wp.array2d(dtype=wp.float64)):
    """One thread per (b, c): :func:`cdf_partial`."""
    b, c = wp.tid()
    cdf_partial(b, c, n_per, logw, stats, sums_out)



@wp.func
def cdf_chunk(b: int, c: int, n_per: int, logw: wp.array(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64),
              sums_in: wp.array2d(dtype=wp.float64), cdf_out: wp.array(dtype=wp.float32)):
    """Filter b (resampling only), chunk c: the inclusive cumulative weights of its particles (float64 sums)."""
    if stats[b, ST_RESAMPLE] == wp.float64(0.0):
        return
    lo, hi = chunk_range(c, n_per)
    s = wp.float64(0.0)
    for k in range(c):
        s += sums_in[b, k]
    for k in range(lo, hi):
        s += wp.float64(wp.exp(logw[b * n_per + k]))
        cdf_out[b * n_per + k] = wp.float32(s)


@wp.kernel
def cdf_kernel(n_per: int, logw: wp.array(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64),
               sums_in: wp.array2d(dtype=wp.float64), cdf_out: wp.array(dtype=wp.float32)):
    """One thread per (b, c): :func:`cdf_chunk`."""
    b, c = wp.tid()
    cdf_chunk(b, c, n_per, logw, stats, sums_in, cdf_out)


@wp.func
def ancestor(
    i: int,
    n_per: int,
    stage: int,
    seeds: wp.array(dtype=wp.int32),
    scheme: int,
    stats: wp.array2d(dtype=wp.float64),
    cdf: wp.array(dtype=wp.float32),
    ancestors_out: wp.array(dtype=wp.int32),
):
    """Ancestor of slot j of a resampling filter: 0 systematic ``(j + U)/n`` (one U), 1 stratified
    ``(j + U_j)/n``, 2 multinomial ``U_j``; a filter that does not resample keeps its particles. Random
    streams: ``stage · 2n + j``."""
    b = i // n_per
    j = i % n_per
    if stats[b, ST_RESAMPLE] == wp.float64(0.0):
        ancestors_out[i] = i
        return
    lo = b * n_per
    base = stage * 2 * n_per
    total = cdf[lo + n_per - 1]
    u = float(0.0)
    if scheme == 0:
        shared = wp.rand_init(seeds[b], base)
        u = (float(j) + wp.randf(shared)) / float(n_per)
    elif scheme == 1:
        own = wp.rand_init(seeds[b], base + j)
        u = (float(j) + wp.randf(own)) / float(n_per)
    else:
        own = wp.rand_init(seeds[b], base + j)
        u = wp.randf(own)
    ancestors_out[i] = search_cdf(cdf, lo, lo + n_per, u * total)


@wp.kernel
def ancestors_kernel(
    n_per: int,
    stage: int,
    seeds: wp.array(dtype=wp.int32),
    scheme: int,
    stats: wp.array2d(dtype=wp.float64),
    cdf: wp.array(dtype=wp.float32),
    ancestors_out: wp.array(dtype=wp.int32),
):
    """One thread per (i): :func:`ancestor`."""
    i = wp.tid()
    ancestor(i, n_per, stage, seeds, scheme, stats, cdf, ancestors_out)


@wp.func
def gathered(
    i: int,
    n_per: int,
    stage: int,
    seeds: wp.array(dtype=wp.int32),
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    ancestors: wp.array(dtype=wp.int32),
    dp_in: wp.array(dtype=wp.vec3),
    lin_in: wp.array(dtype=vec12),
    logw_in: wp.array(dtype=wp.float32),
):
    """Slot i's particle after a resampling of its filter: its ancestor's, with uniform weights and the regularisation
    jitter with (partial) kernel shrinkage (Liu & West 2001): ``dp = a dp_anc + (1 - a) m + h chol(Σ̂) z``,
    ``a = sqrt(1 - s h²)``, ``h`` the bandwidth times the stage's ``ST_JITTER`` (:data:`JITTER_NIS`), Σ̂ and m the
    weighted covariance and mean of dp before resampling (stream
    ``stage · 2n + n + j``): the mean is kept and the covariance grows by ``1 + (1 - s) h² f`` (``f`` the stage's
    ``ST_INFLATE``: 1 unless the cloud would pass the unaided INS's horizontal variance,
    :func:`warptan.kernels.filter.weights.weight_stats`).
    The Kalman mean is the ancestor's (see :mod:`warptan.filter.mpf`). In other filters its own (the ancestor is
    the slot). Returns (dp, l, log-weight)."""
    b = i // n_per
    a = ancestors[i]
    d = dp_in[a]
    lw = logw_in[a]
    if stats[b, ST_RESAMPLE] != wp.float64(0.0):
        lw = -wp.log(float(n_per))
        h = params.bandwidth * wp.float32(stats[b, ST_JITTER])
        if h > 0.0:
            state = wp.rand_init(seeds[b], stage * 2 * n_per + n_per + i % n_per)
            s_eff = 1.0 - (1.0 - params.shrinkage) * wp.float32(stats[b, ST_INFLATE])
            shrink = wp.sqrt(wp.max(1.0 - s_eff * h * h, 0.0))
            mean = wp.vec3(wp.float32(stats[b, ST_MEAN_DP]), wp.float32(stats[b, ST_MEAN_DP + 1]),
                           wp.float32(stats[b, ST_MEAN_DP + 2]))
            d = shrink * d + (1.0 - shrink) * mean + h * (stats_chol(stats, b) * gaussian3(state))
    return d, lin_in[a], lw


@wp.func
def gather(
    i: int,
    n_per: int,
    stage: int,
    seeds: wp.array(dtype=wp.int32),
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    ancestors: wp.array(dtype=wp.int32),
    dp_in: wp.array(dtype=wp.vec3),
    lin_in: wp.array(dtype=vec12),
    logw_in: wp.array(dtype=wp.float32),
    dp_out: wp.array(dtype=wp.vec3),
    lin_out: wp.array(dtype=vec12),
    logw_out: wp.array(dtype=wp.float32),
):
    """Slot i takes :func:`gathered` (into other arrays than the ones it reads)."""
    d, lm, lw = gathered(i, n_per, stage, seeds, params, stats, ancestors, dp_in, lin_in, logw_in)
    dp_out[i] = d
    lin_out[i] = lm
    logw_out[i] = lw


@wp.kernel
def gather_kernel(
    n_per: int,
    stage: int,
    seeds: wp.array(dtype=wp.int32),
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    ancestors: wp.array(dtype=wp.int32),
    dp_in: wp.array(dtype=wp.vec3),
    lin_in: wp.array(dtype=vec12),
    logw_in: wp.array(dtype=wp.float32),
    dp_out: wp.array(dtype=wp.vec3),
    lin_out: wp.array(dtype=vec12),
    logw_out: wp.array(dtype=wp.float32),
):
    """One thread per (i): :func:`gather`."""
    i = wp.tid()
    gather(i, n_per, stage, seeds, params, stats, ancestors, dp_in, lin_in, logw_in, dp_out, lin_out, logw_out)



@wp.func
def copy_particle(i: int, dp_in: wp.array(dtype=wp.vec3), lin_in: wp.array(dtype=vec12),
                  logw_in: wp.array(dtype=wp.float32), dp_out: wp.array(dtype=wp.vec3),
                  lin_out: wp.array(dtype=vec12), logw_out: wp.array(dtype=wp.float32)):
    dp_out[i] = dp_in[i]
    lin_out[i] = lin_in[i]
    logw_out[i] = logw_in[i]


@wp.kernel
def copy_particles_kernel(dp_in: wp.array(dtype=wp.vec3), lin_in: wp.array(dtype=vec12),
                          logw_in: wp.array(dtype=wp.float32), dp_out: wp.array(dtype=wp.vec3),
                          lin_out: wp.array(dtype=vec12), logw_out: wp.array(dtype=wp.float32)):
    """:func:`copy_particle`, one thread per i."""
    i = wp.tid()
    copy_particle(i, dp_in, lin_in, logw_in, dp_out, lin_out, logw_out)


@wp.kernel
def gather_modes_kernel(ancestors: wp.array(dtype=wp.int32), mean_in: wp.array(dtype=modes_vec),
                        post_in: wp.array(dtype=modes_vec), mean_out: wp.array(dtype=modes_vec),
                        post_out: wp.array(dtype=modes_vec)):
    """Slot i takes its ancestor's map-error mode amplitudes: the prior it was weighted with and its posterior (the
    map error under a hypothesis belongs to the hypothesis). The separate-kernel form; the stage block gathers them
    itself (:func:`~warptan.kernels.filter.blocks.gather_modes_lanes`)."""
    i = wp.tid()
    a = ancestors[i]
    mean_out[i] = mean_in[a]
    post_out[i] = post_in[a]


@wp.kernel
def copy_modes_kernel(mean_in: wp.array(dtype=modes_vec), post_in: wp.array(dtype=modes_vec),
                      mean_out: wp.array(dtype=modes_vec), post_out: wp.array(dtype=modes_vec)):
    i = wp.tid()
    mean_out[i] = mean_in[i]
    post_out[i] = post_in[i]


@wp.kernel
def keep_done_modes_kernel(n_per: int, stats: wp.array2d(dtype=wp.float64), held: wp.array(dtype=modes_vec),
                           post: wp.array(dtype=modes_vec)):
    """After a tempering stage's model launch: the filters of a batch that were done before it (no exponent left)
    take back the mode posteriors ``held`` copied before it. The launch evaluates every filter's particles, and a done
    filter's regularised particles would otherwise carry a posterior evaluated at their jittered poses rather than
    their ancestors' (what the filter run alone keeps): a batch must give each filter's bits as alone."""
    i = wp.tid()
    if stats[i // n_per, ST_REMAIN] <= wp.float64(0.0):
        post[i] = held[i]


@wp.func
def modes_finalize(
    i: int,
    n_per: int,
    m: int,
    table: wp.array(dtype=modes_vec),
    stats: wp.array2d(dtype=wp.float64),
    post: wp.array(dtype=modes_vec),
    var: wp.array(dtype=modes_vec),
    mean: wp.array(dtype=modes_vec),
):
    """After an update (and a re-spread): particle i's map-error mode amplitudes for the next scan. Applied: the
    model's ``ρ_i q_i`` (:func:`warptan.kernels.likelihood.mode_post`); skipped: the prediction alone (``μ ← ρ T
    μ``); re-spread: zero. Before :func:`modes_variance` (it reads the filter's variances unchanged)."""
    b = i // n_per
    if stats[b, ST_RESPREAD] != wp.float64(0.0):
        mean[i] = modes_vec()
    elif stats[b, ST_SKIP] != wp.float64(0.0):
        mu, _pv = mode_prior(table, m, mean[i], var[b])
        mean[i] = wp.cw_mul(table[m + MODE_RHO], mu)
    else:
        mean[i] = post[i]


@wp.kernel
def modes_finalize_kernel(n_per: int, m: int, table: wp.array(dtype=modes_vec), stats: wp.array2d(dtype=wp.float64),
                          post: wp.array(dtype=modes_vec), var: wp.array(dtype=modes_vec),
                          mean: wp.array(dtype=modes_vec)):
    """:func:`modes_finalize`, one thread per particle."""
    modes_finalize(wp.tid(), n_per, m, table, stats, post, var, mean)


@wp.func
def modes_variance(b: int, m: int, table: wp.array(dtype=modes_vec), stats: wp.array2d(dtype=wp.float64),
                   var: wp.array(dtype=modes_vec)):
    """Filter b's variances of its mode amplitudes for the next scan: applied, ``P_i ← ρ_i² P⁻_i / (1 + P⁻_i) + (1 −
    ρ_i²) k⁰_i`` (the Kalman update of independent modes of unit noise, then a first-order step along the track);
    skipped, the step alone; re-spread (or none yet and skipped): none (negative: the next scan starts from the
    one-scan prior ``k⁰``)."""
    skipped = stats[b, ST_SKIP] != wp.float64(0.0)
    if stats[b, ST_RESPREAD] != wp.float64(0.0) or (skipped and var[b][0] < 0.0):
        var[b] = modes_vec(-1.0)
        return
    rho = table[m + MODE_RHO]
    k0 = table[m + MODE_K0]
    _mu, pv = mode_prior(table, m, modes_vec(), var[b])
    v = modes_vec()
    for k in range(MAX_MODES):
        after = pv[k]
        if not skipped:
            after = pv[k] / (1.0 + pv[k])
        v[k] = rho[k] * rho[k] * after + (1.0 - rho[k] * rho[k]) * k0[k]
    var[b] = v


@wp.kernel
def modes_variance_kernel(m: int, table: wp.array(dtype=modes_vec), stats: wp.array2d(dtype=wp.float64),
                          var: wp.array(dtype=modes_vec)):
    """:func:`modes_variance`, one thread per filter."""
    modes_variance(wp.tid(), m, table, stats, var)


MOMENTS_LEN = 6
"""Columns of :func:`map_error_moments_kernel`'s output: Σ w, the weighted mean NIS, the mean ratio of the data-ruled
modes' second moments to their stated variance, how many modes it averaged, the weighted variance of the
particles' north and east position errors (m²)."""


@wp.kernel
def map_error_moments_kernel(n_per: int, m: int, table: wp.array(dtype=modes_vec), logw: wp.array(dtype=wp.float32),
                             dp: wp.array(dtype=wp.vec3), nis: wp.array(dtype=wp.float32),
                             mean: wp.array(dtype=modes_vec), var: wp.array(dtype=modes_vec),
                             reads: wp.array(dtype=modes_vec), out: wp.array2d(dtype=wp.float64)):
    """Filter b's evidence on its stated map error after an update (one thread per filter; the host's
    :class:`warptan.sensing.learner.MapErrorLearner` reads it every few updates). The modes' amplitudes are
    stored predicted to the next scan (mean ``ρ_i q_i``, variance ``ρ_i² P⁺_i + (1 − ρ_i²) k⁰_i``,
    :func:`modes_variance_kernel`); their posterior second moment ``E[α_i²] = Σ_j w_j q_ij² + P⁺_i`` over the stated
    one-scan variance ``k⁰_i`` is 1 on average when the statement is right (the fixed point of an EM step for the
    error's variance), ``(1 + k_true) / k⁰`` when not. Only modes the scan rules (``k⁰_i ≥ 1``) and ``reads[0]``
    marks (positive: the modes mostly on points whose sensitivity to the map the table knows,
    :attr:`warptan.sensing.measurement.MeasurementModel.mode_reads`) are averaged: the others stay near their prior
    whatever the map is. Without a variance yet (negative) the ratio is 0 over 0 modes."""
    b = wp.tid()
    rho = table[m + MODE_RHO]
    k0 = table[m + MODE_K0]
    sw = wp.float64(0.0)
    s_nis = wp.float64(0.0)
    s_dp = wp.vec2d()
    s_dp2 = wp.vec2d()
    s_q2 = modes_vec()
    for k in range(n_per):
        i = b * n_per + k
        w = wp.float64(wp.exp(logw[i]))
        sw += w
        if wp.isfinite(nis[i]):
            s_nis += w * wp.float64(nis[i])
        d = wp.vec2d(wp.float64(dp[i][0]), wp.float64(dp[i][1]))
        s_dp += w * d
        s_dp2 += w * wp.cw_mul(d, d)
        s_q2 += float(w) * wp.cw_mul(mean[i], mean[i])
    inv = wp.float64(1.0) / wp.max(sw, wp.float64(1.0e-300))
    ratio = wp.float64(0.0)
    used = int(0)
    v = var[b]
    if v[0] >= 0.0:
        for j in range(MAX_MODES):
            r2 = rho[j] * rho[j]
            if k0[j] >= 1.0 and r2 > 0.0 and reads[0][j] > 0.0:
                post_var = wp.max((v[j] - (1.0 - r2) * k0[j]) / r2, 0.0)
                second = float(s_q2[j] * float(inv)) / r2 + post_var
                ratio += wp.float64(second / k0[j])
                used += 1
    mn = s_dp * inv
    out[b, 0] = sw
    out[b, 1] = s_nis * inv
    out[b, 2] = ratio / wp.float64(wp.max(used, 1))
    out[b, 3] = wp.float64(used)
    out[b, 4] = s_dp2[0] * inv - mn[0] * mn[0]
    out[b, 5] = s_dp2[1] * inv - mn[1] * mn[1]


PROJ_LEN = MAX_MODES + 3
"""Columns of :func:`mode_projection_kernel`'s output: each mode's Σ w p_i², Σ w, Σ w h (the residuals' energy
outside the modes per degree of freedom) and Σ w over the particles with that energy."""
PROJ_SW = MAX_MODES
WHITE_MAX_GAIN = 1.5
"""The largest sensitivity to the map (a ray's 1/u_z: within 48° of the vertical) of a point that reads the map's white
error in :func:`mode_projection_kernel`: farther from the vertical the ray's own slope-dependent sensitivity departs
from 1/u_z (by a third on a 0.3 slope at 48°) and its share of the stated error the modes cannot hold (``ray_var``'s
excess) would read as white error."""
PROJ_HF = MAX_MODES + 1
PROJ_HF_W = MAX_MODES + 2


@wp.kernel
def loglik_max_kernel(n_per: int, loglik: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.float32)):
    """Filter b's largest finite log-likelihood of the last evaluation (the reference of
    :func:`mode_projection_kernel`'s weights; −inf when none)."""
    b = wp.tid()
    best = float(-wp.inf)
    for k in range(n_per):
        v = loglik[b * n_per + k]
        if wp.isfinite(v):
            best = wp.max(best, v)
    out[b] = best


@wp.kernel
def mode_projection_kernel(n_per: int, m: int, table: wp.array(dtype=modes_vec),
                           residual: wp.array2d(dtype=wp.float32), loglik: wp.array(dtype=wp.float32),
                           ref: wp.array(dtype=wp.float32), sigma: float, gate: float,
                           quat_nb: wp.array(dtype=wp.vec4), cloud: wp.array2d(dtype=cloud_row), ray: int,
                           out: wp.array2d(dtype=wp.float64)):
    """Particle t's raw projections of its last residuals on the scan's map-error modes, ``p_i = Σ_j u_ji z_j``, ``z_j =
    r_j / σ`` (a point not received, not hit, beyond ``gate`` whitened, or not held by the modes (a zero row of the
    table): none), weighted by its likelihood ``w = exp(ℓ_t − max ℓ)`` into filter b's ``Σ w p_i²`` (``out[b, i]``)
    and ``Σ w`` (``out[b, PROJ_SW]``), zeroed by the caller. Unlike the modes' posterior moments
    (:func:`map_error_moments_kernel`) these do not lean on the statement's variances: the evidence on the error's
    correlation length (:meth:`warptan.sensing.learner.MapErrorLearner.read`).

    Also the energy the modes and the offset leave, per degree of freedom and per unit of sensitivity to the map:
    ``h = (Σ_j z_j² − n z̄² − Σ_i p_i²) / (n − 1 − M) · (1/n) Σ_j a_j⁻²`` over the ``n`` points used (``M =
    MAX_MODES``; the offset as the mean, exact where every point's sensitivity ``a_j`` is 1; ``a_j`` the ray's
    ``ray_nominal_gain`` 1/u_z under the particle's attitude ``quat_nb[t]`` and the scan's directions ``cloud`` with
    ``ray``, else 1: a ray far from the vertical reads the map's white error magnified; only the points with ``a_j ≤
    WHITE_MAX_GAIN``, their own projections ``p_i`` too), into ``Σ w h`` (``out[b,
    PROJ_HF]``) and ``Σ w`` (``out[b, PROJ_HF_W]``) over the particles with ``n > M + 1``: the evidence on the map's
    white error (what varies from post to post)."""
    t = wp.tid()
    b = t // n_per
    lt = loglik[t]
    if not wp.isfinite(lt) or not wp.isfinite(ref[b]):
        return
    w = wp.exp(wp.float64(lt - ref[b]))
    p = modes_vec()
    q = modes_vec()  # (the projections of the points that read the white error)
    inv = 1.0 / sigma
    mat = quat_to_mat_wxyz(quat_nb[t])
    s1 = float(0.0)
    s2 = float(0.0)
    s_inv_a2 = float(0.0)
    n = int(0)
    for j in range(m):
        z = residual[t, j] * inv
        u = table[j]
        if wp.isfinite(z) and wp.abs(z) <= gate and wp.dot(u, u) > 0.0:
            a = float(1.0)
            if ray != 0:
                a = ray_nominal_gain((mat * row_dir(cloud[b, j]))[2])
            p += u * z
            if a <= WHITE_MAX_GAIN:
                q += u * z
                s1 += z
                s2 += z * z
                s_inv_a2 += 1.0 / (a * a)
                n += 1
    pp = float(0.0)
    for i in range(MAX_MODES):
        pp += q[i] * q[i]
        wp.atomic_add(out, b, i, w * wp.float64(p[i] * p[i]))
    wp.atomic_add(out, b, PROJ_SW, w)
    if n > MAX_MODES + 1:
        h = wp.max(s2 - s1 * s1 / float(n) - pp, 0.0) / float(n - 1 - MAX_MODES) * s_inv_a2 / float(n)
        wp.atomic_add(out, b, PROJ_HF, w * wp.float64(h))
        wp.atomic_add(out, b, PROJ_HF_W, w)
