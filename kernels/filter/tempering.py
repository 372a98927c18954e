"""Tempering: the statistics' reset, the candidates' streaming log-sum-exp partials, the ESS each leaves and the
stage's exponent (Oudjane & Musso 2000)."""

import warp as wp

from warptan.kernels.block import on_cuda, warp_max, warp_sum
from warptan.kernels.filter.common import (
    N_CHUNKS,
    N_STATS,
    N_TEMPER,
    ST_ACTIVE,
    ST_APPLIED,
    ST_GAMMA,
    ST_REMAIN,
    ST_RESAMPLE,
    ST_SKIP,
    ST_STAGES,
    TEMPER_RATIO,
    WARP_LANES,
    UpdateParams,
    chunk_range,
    stage_loglik,
)
from warptan.kernels.likelihood import META_FLOOR, META_RECEIVED

wp.set_module_options({"enable_backward": False})

@wp.func
def begin_stats(b: int, exponent: wp.array(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64)):
    """One thread per filter: the log-likelihood's exponent ``exponent[b]`` (1, or less over ground whose map error
    the filter has read before: :class:`warptan.sensing.likelihood.RevisitMemory`) is still to apply; counters
    reset."""
    for k in range(N_STATS):
        stats[b, k] = wp.float64(0.0)
    stats[b, ST_REMAIN] = wp.float64(exponent[b])


@wp.kernel
def begin_update_kernel(exponent: wp.array(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64)):
    """One thread per (b): :func:`begin_stats`."""
    b = wp.tid()
    begin_stats(b, exponent, stats)



@wp.kernel
def more_stages_kernel(stats: wp.array2d(dtype=wp.float64), flag_out: wp.array(dtype=wp.int32)):
    """One thread: ``flag_out[0] = 1`` when some filter still has exponent to apply (the condition of the next
    tempering stage in a captured graph)."""
    more = int(0)
    for b in range(stats.shape[0]):
        if stats[b, ST_REMAIN] > wp.float64(0.0):
            more = 1
    flag_out[0] = more


@wp.func
def temper_partial(
    b: int,
    c: int,
    g: int,
    n_per: int,
    stage: int,
    loglik: wp.array(dtype=wp.float32),
    n_valid: wp.array(dtype=wp.int32),
    meta: wp.array2d(dtype=wp.float32),
    logw: wp.array(dtype=wp.float32),
    stats: wp.array2d(dtype=wp.float64),
    partial_out: wp.array4d(dtype=wp.float64),
    unpred_out: wp.array2d(dtype=wp.float64),
):
    """Filter b, chunk c, candidate exponent ``γ_g``: streaming log-sum-exp partials ``[max, Σe, Σe²]`` of
    ``logw_i + γ_g loglik_i`` (rescaled to the running maximum), and at stage 0 (``g == 0``) the weighted fraction of
    the received points the particles cannot predict."""
    rem = stats[b, ST_REMAIN]
    if stage > 0 and rem <= wp.float64(0.0):
        return
    lo, hi = chunk_range(c, n_per)
    floor = meta[b, META_FLOOR]
    if g == 0:
        n_recv = wp.float64(meta[b, META_RECEIVED])
        unpred = wp.float64(0.0)
        if stage == 0 and n_recv > wp.float64(0.0):
            for k in range(lo, hi):
                i = b * n_per + k
                unpred += wp.float64(wp.exp(logw[i])) * (wp.float64(1.0) - wp.float64(n_valid[i]) / n_recv)
        unpred_out[b, c] = unpred
    gamma = rem
    for _ in range(g):
        gamma = gamma * wp.float64(TEMPER_RATIO)
    m = wp.float64(-1.0e300)
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    for k in range(lo, hi):
        i = b * n_per + k
        x = wp.float64(logw[i]) + gamma * wp.float64(stage_loglik(loglik[i], floor))
        if x > m:
            scale = wp.exp(m - x)
            s1 = s1 * scale + wp.float64(1.0)
            s2 = s2 * scale * scale + wp.float64(1.0)
            m = x
        else:
            e = wp.exp(x - m)
            s1 += e
            s2 += e * e
    partial_out[b, c, g, 0] = m
    partial_out[b, c, g, 1] = s1
    partial_out[b, c, g, 2] = s2


@wp.kernel
def temper_partials_kernel(
    n_per: int,
    stage: int,
    loglik: wp.array(dtype=wp.float32),
    n_valid: wp.array(dtype=wp.int32),
    meta: wp.array2d(dtype=wp.float32),
    logw: wp.array(dtype=wp.float32),
    stats: wp.array2d(dtype=wp.float64),
    partial_out: wp.array4d(dtype=wp.float64),
    unpred_out: wp.array2d(dtype=wp.float64),
):
    """:func:`temper_partial` of every candidate at once, one thread per (filter, chunk, candidate) (CUDA): one per
    (filter, chunk) looping over the 20 candidates took 55 µs per stage on an H100 at N = 500 (64 threads per
    filter)."""
    b, c, g = wp.tid()
    temper_partial(b, c, g, n_per, stage, loglik, n_valid, meta, logw, stats, partial_out, unpred_out)


@wp.func
def temper_ess_of(b: int, g: int, partial_in: wp.array4d(dtype=wp.float64), ess_out: wp.array2d(dtype=wp.float64)):
    """The ESS candidate g of filter b would leave, from the chunks' streaming partials."""
    big = partial_in[b, 0, g, 0]
    for c in range(N_CHUNKS):
        big = wp.max(big, partial_in[b, c, g, 0])
    s1 = wp.float64(0.0)
    s2 = wp.float64(0.0)
    for c in range(N_CHUNKS):
        scale = wp.exp(partial_in[b, c, g, 0] - big)
        s1 += partial_in[b, c, g, 1] * scale
        s2 += partial_in[b, c, g, 2] * scale * scale
    ess_out[b, g] = s1 * s1 / s2


@wp.func
def temper_ess_lanes(b: int, g: int, lane: int, partial_in: wp.array4d(dtype=wp.float64),
                     ess_out: wp.array2d(dtype=wp.float64)):
    """:func:`temper_ess_of` by the 32 lanes of a CUDA warp (``lane`` in [0, 32); every lane must call it): lane l
    takes chunks l and l + 32, the maximum and the two sums go through the warp's butterfly
    (:func:`~warptan.kernels.block.warp_sum`: a pairwise tree over the chunks, the same bits in every lane and
    launch form). One thread reading the 64 chunks in order took 6.8 µs a stage on an H100 (128 dependent loads
    per candidate). On the CPU (one thread): :func:`temper_ess_of`, the chunks in order."""
    if on_cuda() == 0:
        temper_ess_of(b, g, partial_in, ess_out)
        return
    m0 = partial_in[b, lane, g, 0]
    m1 = partial_in[b, lane + WARP_LANES, g, 0]
    big = warp_max(wp.max(m0, m1))
    e0 = wp.exp(m0 - big)
    e1 = wp.exp(m1 - big)
    s1 = warp_sum(partial_in[b, lane, g, 1] * e0 + partial_in[b, lane + WARP_LANES, g, 1] * e1)
    s2 = warp_sum(partial_in[b, lane, g, 2] * e0 * e0 + partial_in[b, lane + WARP_LANES, g, 2] * e1 * e1)
    if lane == 0:
        ess_out[b, g] = s1 * s1 / s2


@wp.kernel
def temper_ess_kernel(partial_in: wp.array4d(dtype=wp.float64), ess_out: wp.array2d(dtype=wp.float64)):
    """Filter b, candidate g, a warp (``wp.launch_tiled``, ``WARP_LANES`` lanes): :func:`temper_ess_lanes`."""
    b, g, lane = wp.tid()
    temper_ess_lanes(b, g, lane, partial_in, ess_out)


@wp.func
def temper_search(
    b: int,
    n_per: int,
    stage: int,
    params: UpdateParams,
    loglik: wp.array(dtype=wp.float32),
    n_valid: wp.array(dtype=wp.int32),
    meta: wp.array2d(dtype=wp.float32),
    logw: wp.array(dtype=wp.float32),
    stats: wp.array2d(dtype=wp.float64),
    partial_out: wp.array4d(dtype=wp.float64),
    unpred_out: wp.array2d(dtype=wp.float64),
    ess_out: wp.array2d(dtype=wp.float64),
):
    """Filter b's candidates in order, largest exponent first (the CPU's form of :data:`temper_partials_kernel` +
    :data:`temper_ess_kernel`), each scored over every chunk exactly as there, stopping at the first one
    :data:`temper_select_kernel` takes (ESS ≥ ``temper_ess · n``; after the first when tempering is off). The
    selection reads no candidate after that one, so the result is the same bits for a fraction of the work: usually
    one candidate of 20 (the whole exponent keeps the ESS). Nothing for a filter with no exponent left."""
    if stage > 0 and stats[b, ST_REMAIN] <= wp.float64(0.0):
        return
    target = wp.float64(params.temper_ess) * wp.float64(n_per)
    for g in range(N_TEMPER):
        for c in range(N_CHUNKS):
            temper_partial(b, c, g, n_per, stage, loglik, n_valid, meta, logw, stats, partial_out, unpred_out)
        temper_ess_of(b, g, partial_out, ess_out)
        if params.temper_ess <= 0.0 or ess_out[b, g] >= target:
            break


@wp.kernel
def temper_search_kernel(
    n_per: int,
    stage: int,
    params: UpdateParams,
    loglik: wp.array(dtype=wp.float32),
    n_valid: wp.array(dtype=wp.int32),
    meta: wp.array2d(dtype=wp.float32),
    logw: wp.array(dtype=wp.float32),
    stats: wp.array2d(dtype=wp.float64),
    partial_out: wp.array4d(dtype=wp.float64),
    unpred_out: wp.array2d(dtype=wp.float64),
    ess_out: wp.array2d(dtype=wp.float64),
):
    """One thread per filter: :func:`temper_search`."""
    b = wp.tid()
    temper_search(b, n_per, stage, params, loglik, n_valid, meta, logw, stats, partial_out, unpred_out, ess_out)


@wp.func
def temper_select(
    b: int,
    n_per: int,
    stage: int,
    last_stage: int,
    params: UpdateParams,
    meta: wp.array2d(dtype=wp.float32),
    ess_in: wp.array2d(dtype=wp.float64),
    unpred_in: wp.array2d(dtype=wp.float64),
    stats: wp.array2d(dtype=wp.float64),
):
    """One thread per filter: this stage's exponent, the largest candidate that keeps ESS ≥ ``temper_ess · n``
    (the smallest candidate when none does; all that remains when ``temper_ess`` is 0). At stage 0 an update
    with no valid received point, or one whose predictions are mostly impossible (``max_unpredictable``: the
    map does not cover the scan), is skipped: exponent 0. At the last stage what remains is dropped (the
    update is then softer than the likelihood, never sharper)."""
    rem = stats[b, ST_REMAIN]
    stats[b, ST_RESAMPLE] = wp.float64(0.0)
    stats[b, ST_GAMMA] = wp.float64(0.0)
    active = stage == 0 or rem > wp.float64(0.0)
    stats[b, ST_ACTIVE] = wp.float64(0.0)
    if not active:
        return
    stats[b, ST_ACTIVE] = wp.float64(1.0)
    if stage == 0:
        frac = wp.float64(0.0)
        for c in range(N_CHUNKS):
            frac += unpred_in[b, c]
        if meta[b, META_RECEIVED] <= 0.0 or frac > wp.float64(params.max_unpredictable):
            stats[b, ST_SKIP] = wp.float64(1.0)
            stats[b, ST_REMAIN] = wp.float64(0.0)
            return
    gamma = rem
    if params.temper_ess > 0.0:
        target = wp.float64(params.temper_ess) * wp.float64(n_per)
        cand = rem
        found = int(0)
        for g in range(N_TEMPER):
            if found == 0:
                gamma = cand
                if ess_in[b, g] >= target:
                    found = 1
                cand = cand * wp.float64(TEMPER_RATIO)
    left = rem - gamma
    if gamma >= rem or last_stage != 0:
        left = wp.float64(0.0)
    stats[b, ST_GAMMA] = gamma
    stats[b, ST_REMAIN] = left
    stats[b, ST_APPLIED] = stats[b, ST_APPLIED] + gamma
    stats[b, ST_STAGES] = stats[b, ST_STAGES] + wp.float64(1.0)


@wp.kernel
def temper_select_kernel(
    n_per: int,
    stage: int,
    last_stage: int,
    params: UpdateParams,
    meta: wp.array2d(dtype=wp.float32),
    ess_in: wp.array2d(dtype=wp.float64),
    unpred_in: wp.array2d(dtype=wp.float64),
    stats: wp.array2d(dtype=wp.float64),
):
    """One thread per (b): :func:`temper_select`."""
    b = wp.tid()
    temper_select(b, n_per, stage, last_stage, params, meta, ess_in, unpred_in, stats)
