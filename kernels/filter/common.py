"""Shared by the filter's kernels (:mod:`warptan.kernels.mpf`): the layout of the per-filter statistics, records and
feedback (``ST_*``, ``H_*``, ``FB_*``, ``IN_*``, ``NOM_*``), the update's parameters, chunking, Gaussian draws and
small float64 helpers."""

import warp as wp

from warptan.kernels.block import on_cuda, warp_sum

wp.set_module_options({"enable_backward": False})

vec12 = wp.types.vector(length=12, dtype=wp.float32)

N_CHUNKS = wp.constant(64)
"""Partial sums per filter in the weight reductions (threads of their first stage, per filter)."""
WARP_LANES = wp.constant(32)
"""Lanes of a CUDA warp. A chunk reduction on CUDA is one warp's: lane l takes chunks l and l + 32
(``N_CHUNKS`` = 2 × ``WARP_LANES``), then the warp's butterfly (:func:`warptan.kernels.block.warp_sum`)."""
assert N_CHUNKS == 2 * WARP_LANES
N_CHUNK_SUMS = wp.constant(21)
"""Values per chunk of the weight reductions: Σe, Σe², Σe dp (3), Σe dp∘dp (3), Σe (xy, xz, yz), Σe nis,
Σe Λ (6: 00 11 22 01 02 12), Σe I_p (3: nn ee ne; the position information of a model that cannot fix the position
with one measurement, else 0)."""
N_SUMMARY_SUMS = wp.constant(34)
"""Values per chunk of the record's reduction: Σw, Σw dp (3), Σw dp∘dp (3), Σw (xy, xz, yz), Σw l (12),
Σw l∘l (12)."""
chunk_vec = wp.types.vector(length=21, dtype=wp.float64)
summary_vec = wp.types.vector(length=34, dtype=wp.float64)
"""The chunk sums of one filter, reduced by a block (lanes over the chunks; one thread in order on the CPU). One
thread per filter reading the 64 chunks took 34 µs per reduction on an H100 (latency of 1 152 serial loads)."""
N_MOMENT_CHUNKS = wp.constant(16)
"""Partial sums per filter of the moments of the estimate."""
N_MOMENTS = wp.constant(1 + 3 + 9 + 12 + 144)
"""Moments reduced for the estimate: Σw, Σw dp, Σw dp dpᵀ, Σw l, Σw l lᵀ (offsets below)."""
MOM_W = wp.constant(0)  # Σw
MOM_DP = wp.constant(1)  # 3 values: Σw dp
MOM_DPDP = wp.constant(4)  # 9 values: Σw dp dpᵀ, row-major
MOM_L = wp.constant(13)  # 12 values: Σw l
MOM_LL = wp.constant(25)  # 144 values: Σw l lᵀ, row-major
NOM_POS = wp.constant(0)
"""Columns of the nominal history (16 per filter and update): p (3), v (3), q (4), b_a (3), b_g (3)."""
NOM_VEL = wp.constant(3)
NOM_QUAT = wp.constant(6)
NOM_BA = wp.constant(10)
NOM_BG = wp.constant(13)
N_NOMINAL = 16
N_TEMPER = wp.constant(20)
"""Candidate exponents of a tempering stage: ``γ_k = remaining · TEMPER_RATIO^k``."""
JITTER_NIS = wp.constant(1.0)
"""A model that cannot fix the position with one measurement (the altimeter: a contour per reading) is found from the
accumulated profile, which each particle's weight carries; a resampled particle keeps its ancestor's weight, which
holds only as long as its jitter moves its prediction of the last measurement by no more than about σ. The
regularisation kernel ``h² Σ̂`` is therefore scaled down until ``tr(h² Σ̂ Ī_p) ≤ JITTER_NIS`` (Ī_p the weighted mean
of the particles' horizontal position information, ``g gᵀ / σ²``): Silverman's h on a cloud that the first readings
leave multimodal (tens of metres between contours, σ_pos ~ 100 m) jittered S9 on the 30 m tile ~40 m per
resampling, and the cloud walked off along the contours (4 of 20 seeds lost, up to 6 km). In a cloud that has
converged ``h² Σ̂`` is far inside one measurement's resolution and nothing changes."""
TEMPER_RATIO = wp.constant(0.57434918)  # 2^-0.8: the smallest candidate is 2^-15.2 ≈ 2.7e-5 of the remaining

# ---- per-filter statistics of an update (columns of ``stats``)
N_STATS = wp.constant(33)
ST_ESS = wp.constant(0)  # ESS after the last applied stage's weights (before its resampling)
ST_LOGNORM = wp.constant(1)
ST_BAD = wp.constant(2)  # particles whose log-likelihood was not finite (scored the floor)
ST_MAX = wp.constant(3)
ST_UNPREDICTABLE = wp.constant(4)  # particles that could predict no received point
ST_MEAN_DP = wp.constant(5)  # 3 values: the weighted mean of dp (before resampling)
ST_RESPREAD = wp.constant(8)  # the integrity monitor re-spread the filter at the end of this update
ST_RESAMPLE = wp.constant(9)  # this stage resamples
ST_CHOL = wp.constant(10)  # 6 values: lower Cholesky factor of the weighted covariance of dp (00 10 11 20 21 22)
ST_REMAIN = wp.constant(16)  # exponent of the log-likelihood still to apply in this update
ST_GAMMA = wp.constant(17)  # exponent of this stage
ST_ACTIVE = wp.constant(18)  # this stage changes the filter
ST_STAGES = wp.constant(19)  # stages applied in this update
ST_RESAMPLES = wp.constant(20)  # resamplings in this update
ST_SKIP = wp.constant(21)  # the update carried no usable information (see temper_select_kernel)
ST_NIS = wp.constant(22)  # posterior-weighted normalised squared residual
ST_APPLIED = wp.constant(23)  # total exponent applied
ST_JITTER = wp.constant(24)  # the regularisation bandwidth's factor in this stage's resampling (≤ 1; JITTER_NIS)
ST_NIS_MIN = wp.constant(25)  # smallest NIS of any particle (the integrity monitor's input)
ST_LAM = wp.constant(26)  # 6 values: weighted mean of the particles' attitude information Λ (00 11 22 01 02 12)
ST_INFLATE = wp.constant(32)  # share of the shrinkage's growth this stage's resampling keeps (≤ 1; free_var)

# ---- persistent integrity state per filter (columns of ``integrity``)
MAX_WINDOW = wp.constant(64)
N_INTEGRITY = wp.constant(3 + 64)
IN_MEAN = wp.constant(0)  # mean smallest NIS over the last ``window`` informative updates
IN_SINCE = wp.constant(1)  # informative updates since the start or the last re-spread
IN_RESPREADS = wp.constant(2)  # re-spreads so far
IN_RING = wp.constant(3)  # MAX_WINDOW values: the last smallest-NIS values (ring, index since % window)

# ---- per-filter record of an update (columns of ``history``)
N_SUMMARY = wp.constant(45)
H_ESS = wp.constant(0)  # ESS of the last applied stage (before its resampling)
H_RESAMPLES = wp.constant(1)  # resamplings in the update
H_RESPREAD = wp.constant(2)  # 1: the integrity monitor declared the filter lost and re-spread it
H_BAD = wp.constant(3)  # particles with a non-finite log-likelihood
H_UNPREDICTABLE = wp.constant(4)  # particles that could predict no received point
H_SUM_W = wp.constant(5)
H_MEAN_DP = wp.constant(6)  # 3 values: weighted mean of dp after the update, m
H_COV_DP = wp.constant(9)  # 6 values: its covariance xx yy zz xy xz yz, m²
H_STAGES = wp.constant(15)  # tempering stages applied
H_NIS = wp.constant(16)  # smallest normalised squared residual of any particle (best hypothesis)
H_NIS_AVG = wp.constant(17)  # its window mean (the integrity statistic)
H_SKIPPED = wp.constant(18)  # 1: the update carried no usable information and changed nothing
H_APPLIED = wp.constant(19)  # exponent of the likelihood applied (1 unless skipped, capped or revisited)
H_NIS_POST = wp.constant(20)  # posterior-weighted normalised squared residual
H_MEAN_L = wp.constant(21)  # 12 values: weighted mean of the Kalman means l after the update
H_VAR_L = wp.constant(33)  # 12 values: weighted variance of the Kalman means (their spread; P is on the host)

# ---- what the host reads back after an update (columns of ``feedback``): the Kalman covariance's
# measurement update and the closed loop's injection
N_FEEDBACK = wp.constant(23)
FB_APPLIED = wp.constant(0)  # exponent of the likelihood applied (0: skipped, no measurement update of P)
FB_LAM = wp.constant(1)  # 6 values: Λ̄, the weighted mean attitude information (00 11 22 01 02 12), rad⁻²
FB_MEAN_DP = wp.constant(7)  # 3 values: weighted mean of dp after the update, m
FB_MEAN_L = wp.constant(10)  # 12 values: weighted mean of l after the update
FB_CONVERGED = wp.constant(22)  # 1: the integrity monitor has judged the filter and finds it consistent


@wp.struct
class UpdateParams:
    """How a measurement update weights, tempers, resamples and monitors (see :mod:`warptan.filter.mpf`)."""

    resample_threshold: float  # resample when ESS < this · n
    temper_ess: float  # a tempering stage keeps ESS ≥ this · n (0: one stage with the whole likelihood)
    bandwidth: float  # regularisation kernel bandwidth h (0: none)
    shrinkage: float  # kernel shrinkage fraction s: the covariance grows by 1 + (1 - s) h² per resampling
    max_unpredictable: float  # skip the update when more than this fraction of the predictions is impossible
    integrity_window: int  # informative updates in the window mean of the smallest NIS (≤ MAX_WINDOW)
    integrity_threshold: float  # the filter is lost when the window mean exceeds this
    gate_linear: int  # 1: the linear states' measurement update waits for the integrity monitor's consistent verdict
    integrity_min_updates: int  # informative updates (since the start / a re-spread) before it may be declared lost
    respread_chol: wp.mat33  # Cholesky factor of the re-spread covariance of dp, m
    respread_ins: int  # 1: a re-spread always gives the INS half its slots; 0: only where the estimate is implausible
    free_var: wp.array(dtype=wp.float32)  # (B,) horizontal variance of the unaided INS's position error, m²


@wp.func
def chunk_span(c: int, n: int, chunks: int):
    """Items ``[lo, hi)`` of chunk c of n items split into ``chunks`` chunks of one size (the last ones short)."""
    size = (n + chunks - 1) // chunks
    lo = wp.min(c * size, n)
    return lo, wp.min(lo + size, n)


@wp.func
def chunk_range(c: int, n: int):
    """Particles ``[lo, hi)`` (within a filter of n) of chunk c of the weight reductions' ``N_CHUNKS``."""
    return chunk_span(c, n, N_CHUNKS)


stats_vec = wp.types.vector(length=33, dtype=wp.float64)
"""A filter's row of the statistics (``N_STATS`` values) in registers."""


@wp.func
def stats_row(stats: wp.array2d(dtype=wp.float64), b: int) -> stats_vec:
    """Filter b's statistics read at once: independent loads, one round trip, before a piece's stores (a load after
    a store waits for it)."""
    r = stats_vec()
    for k in range(N_STATS):
        r[k] = stats[b, k]
    return r


@wp.func
def chunk_sum(b: int, lane: int, a: int, sums_in: wp.array3d(dtype=wp.float64)) -> wp.float64:
    """Value a of filter b's chunk sums, summed over the chunks: on CUDA by the 32 lanes of a warp (``lane`` in
    [0, 32), every lane calls it and gets the total: chunks ``lane`` and ``lane + 32``, then the warp's butterfly);
    on the CPU (one thread) the chunks in order. On an H100 (clock stamps in the stage and record blocks, S8) the
    weight statistics and the record took 7.3 / 6.5 µs with a block's ``wp.tile_sum`` of the 21 / 34 sums, 5.0 / 6.1
    µs with this (the rest is lane 0's chain of stores)."""
    if on_cuda() == 0:
        s = wp.float64(0.0)
        for k in range(N_CHUNKS):
            s += sums_in[b, k, a]
        return s
    return warp_sum(sums_in[b, lane, a] + sums_in[b, lane + WARP_LANES, a])


RANDN_EPS = wp.constant(5.96e-8)
"""Added to the uniform under Box–Muller's logarithm (as ``wp.randn`` does): ``log`` of a number in (0, 1)."""


@wp.func
def normal_pair(u1: float, u2: float):
    """Two independent standard normal numbers from two uniforms in [0, 1) (Box–Muller, both of its outputs: one
    logarithm and square root for two draws where ``wp.randn`` takes one each)."""
    r = wp.sqrt(-2.0 * wp.log(u1 + RANDN_EPS))
    a = 2.0 * wp.pi * u2
    return r * wp.cos(a), r * wp.sin(a)


@wp.func
def gaussian3(state: wp.uint32) -> wp.vec3:
    """Three independent standard normal numbers."""
    a, b = normal_pair(wp.randf(state), wp.randf(state))
    c, _ = normal_pair(wp.randf(state), wp.randf(state))
    return wp.vec3(a, b, c)


@wp.func
def gaussian_blocks(state: wp.uint32):
    """Five independent standard normal vec3 (one state: the draws must share it), from eight Box–Muller pairs (the
    time update drew 15 ``wp.randn``, 170 µs of a 500-particle CPU update)."""
    a0, a1 = normal_pair(wp.randf(state), wp.randf(state))
    a2, b0 = normal_pair(wp.randf(state), wp.randf(state))
    b1, b2 = normal_pair(wp.randf(state), wp.randf(state))
    c0, c1 = normal_pair(wp.randf(state), wp.randf(state))
    c2, d0 = normal_pair(wp.randf(state), wp.randf(state))
    d1, d2 = normal_pair(wp.randf(state), wp.randf(state))
    e0, e1 = normal_pair(wp.randf(state), wp.randf(state))
    e2, _ = normal_pair(wp.randf(state), wp.randf(state))
    return wp.vec3(a0, a1, a2), wp.vec3(b0, b1, b2), wp.vec3(c0, c1, c2), wp.vec3(d0, d1, d2), wp.vec3(e0, e1, e2)


@wp.func
def stage_loglik(ll: float, floor: float) -> float:
    """A particle's log-likelihood, the filter's floor when it is not finite."""
    if wp.isfinite(ll):
        return ll
    return floor


@wp.func
def pair_products(d: wp.vec3d) -> wp.vec3d:
    """(d0 d1, d0 d2, d1 d2): the off-diagonal products of a second moment."""
    return wp.vec3d(d[0] * d[1], d[0] * d[2], d[1] * d[2])


@wp.func
def weighted_cov(inv: wp.float64, m1: wp.vec3d, m2: wp.vec3d, m3: wp.vec3d) -> wp.mat33d:
    """Covariance from 1/Σw (the caller's reciprocal: a float64 division is a chain of its own on CUDA), Σw d, Σw d∘d,
    Σw (d0d1, d0d2, d1d2)."""
    mean = m1 * inv
    xy = m3[0] * inv - mean[0] * mean[1]
    xz = m3[1] * inv - mean[0] * mean[2]
    yz = m3[2] * inv - mean[1] * mean[2]
    return wp.mat33d(m2[0] * inv - mean[0] * mean[0], xy, xz,
                     xy, m2[1] * inv - mean[1] * mean[1], yz,
                     xz, yz, m2[2] * inv - mean[2] * mean[2])


@wp.func
def chol3(a: wp.mat33d) -> wp.mat33d:
    """Lower Cholesky factor of a symmetric 3×3 matrix, semi-definite safe (a non-positive pivot gives a zero
    column)."""
    lo = wp.mat33d()
    for j in range(3):
        d = a[j, j]
        for k in range(j):
            d -= lo[j, k] * lo[j, k]
        if d > wp.float64(0.0):
            d = wp.sqrt(d)
            lo[j, j] = d
            for i in range(j + 1, 3):
                s = a[i, j]
                for k in range(j):
                    s -= lo[i, k] * lo[j, k]
                lo[i, j] = s / d
    return lo


@wp.func
def sym_from(stats: wp.array2d(dtype=wp.float64), b: int, col: int) -> wp.mat33d:
    """The symmetric 3×3 matrix stored as six columns (00 11 22 01 02 12) from ``col``."""
    xy = stats[b, col + 3]
    xz = stats[b, col + 4]
    yz = stats[b, col + 5]
    return wp.mat33d(stats[b, col], xy, xz, xy, stats[b, col + 1], yz, xz, yz, stats[b, col + 2])


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


@wp.func
def stats_chol(stats: wp.array2d(dtype=wp.float64), b: int) -> wp.mat33:
    z = wp.float32(0.0)
    return wp.mat33(wp.float32(stats[b, ST_CHOL]), z, z,
                    wp.float32(stats[b, ST_CHOL + 1]), wp.float32(stats[b, ST_CHOL + 2]), z,
                    wp.float32(stats[b, ST_CHOL + 3]), wp.float32(stats[b, ST_CHOL + 4]),
                    wp.float32(stats[b, ST_CHOL + 5]))
