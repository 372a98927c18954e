"""Marginalized particle filter kernels (SPEC §6; Schön, Gustafsson & Nordlund 2005; paper §IV).

Particle i holds the position error ``dp_i`` (vec3, m) and the mean ``l_i`` (vec12) of its Kalman filter
over ``[dv, dth, dba, dbg]``; the 12×12 covariance is shared and lives on the host (its measurement update reads
the weighted mean attitude information back from ``feedback``). Weights are kept as log-weights.

A batch of B independent filters of n particles each is one array of N = B·n particles, filter-major:
particle i belongs to filter ``b = i // n``. Per-filter values (statistics, decisions) are (B, k) arrays.

Every reduction runs in a fixed order (``N_CHUNKS`` contiguous partial sums per filter in float64, then one
thread per filter combining them), so that the same seed on the same device gives bit-identical results:
no floating-point atomics. Decisions that used to need the host — re-spread a lost filter, resample — are
flags in ``stats`` that the later kernels read, so a whole measurement update runs with no host sync and
can be captured in a graph.
"""

import warp as wp

from warptan.kernels.block import block_sync
from warptan.kernels.frames import quat_exp_wxyz, quat_log_wxyz, quat_mul_wxyz
from warptan.kernels.likelihood import MAX_MODES, META_FLOOR, META_RECEIVED, MODE_K0, MODE_RHO, mode_prior, modes_vec
from warptan.kernels.nav import block_of, quat_mul_exp_d, skew_d

wp.set_module_options({"enable_backward": False})

vec12 = wp.types.vector(length=12, dtype=wp.float32)

N_CHUNKS = wp.constant(64)
"""Partial sums per filter in the weight reductions (threads of their first stage, per filter)."""
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
N_STATS = wp.constant(32)
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


@wp.func
def chunk_range(c: int, n: int):
    """Particles ``[lo, hi)`` (within a filter of n) of chunk c."""
    size = (n + N_CHUNKS - 1) // N_CHUNKS
    lo = wp.min(c * size, n)
    return lo, wp.min(lo + size, n)


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


@wp.func
def move_particle(
    t: int,
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
def time_update_kernel(
    row0: int,
    n_per: int,
    seeds: wp.array(dtype=wp.int32),
    phi: wp.array3d(dtype=wp.mat33),
    chol: wp.array3d(dtype=wp.mat33),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
):
    """One thread per (t): :func:`move_particle`."""
    t = wp.tid()
    move_particle(t, row0, n_per, seeds, phi, chol, dp, lin)



@wp.func
def pose_of_particle(
    i: int,
    n_per: int,
    pose: wp.array2d(dtype=wp.float64),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
    pos_out: wp.array(dtype=wp.vec3),
    quat_out: wp.array(dtype=wp.vec4),
):
    """Hypothetical poses ``p_i = p_nom + dp_i`` (sum in float64), ``q_i = q_nom ⊗ Exp(dth_i)``;
    ``pose[b] = [p_nom (3), q_nom (4)]`` of the particle's filter."""
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
def particle_poses_kernel(
    n_per: int,
    pose: wp.array2d(dtype=wp.float64),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
    pos_out: wp.array(dtype=wp.vec3),
    quat_out: wp.array(dtype=wp.vec4),
):
    """One thread per (i): :func:`pose_of_particle`."""
    i = wp.tid()
    pose_of_particle(i, n_per, pose, dp, lin, pos_out, quat_out)



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
def stage_loglik(ll: float, floor: float) -> float:
    """A particle's log-likelihood, the filter's floor when it is not finite."""
    if wp.isfinite(ll):
        return ll
    return floor


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


@wp.kernel
def temper_ess_kernel(partial_in: wp.array4d(dtype=wp.float64), ess_out: wp.array2d(dtype=wp.float64)):
    """Filter b, candidate g: :func:`temper_ess_of`."""
    b, g = wp.tid()
    temper_ess_of(b, g, partial_in, ess_out)


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
    """One thread per filter (the CPU's form of :data:`temper_partials_kernel` + :data:`temper_ess_kernel`): the
    candidates in order, largest exponent first, each scored over every chunk exactly as there, stopping at the first
    one :data:`temper_select_kernel` takes (ESS ≥ ``temper_ess · n``; after the first when tempering is off). The
    selection reads no candidate after that one, so the result is the same bits for a fraction of the work: usually
    one candidate of 20 (the whole exponent keeps the ESS)."""
    b = wp.tid()
    if stage > 0 and stats[b, ST_REMAIN] <= wp.float64(0.0):
        return
    target = wp.float64(params.temper_ess) * wp.float64(n_per)
    for g in range(N_TEMPER):
        for c in range(N_CHUNKS):
            temper_partial(b, c, g, n_per, stage, loglik, n_valid, meta, logw, stats, partial_out, unpred_out)
        temper_ess_of(b, g, partial_out, ess_out)
        if params.temper_ess <= 0.0 or ess_out[b, g] >= target:
            break


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
def max_of_partials(b: int, max_in: wp.array2d(dtype=wp.float32), counts_in: wp.array3d(dtype=wp.int32),
                    min_nis_in: wp.array2d(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64)):
    """One thread per active filter: the maximum log-weight, bad log-likelihoods, unpredictable particles, the
    smallest NIS."""
    if stats[b, ST_ACTIVE] == wp.float64(0.0):
        return
    m = max_in[b, 0]
    least = min_nis_in[b, 0]
    bad = int(0)
    unpredictable = int(0)
    for k in range(N_CHUNKS):
        m = wp.max(m, max_in[b, k])
        least = wp.min(least, min_nis_in[b, k])
        bad += counts_in[b, k, 0]
        unpredictable += counts_in[b, k, 1]
    stats[b, ST_NIS_MIN] = wp.float64(least)
    stats[b, ST_BAD] = wp.float64(bad)
    stats[b, ST_UNPREDICTABLE] = wp.float64(unpredictable)
    stats[b, ST_MAX] = wp.float64(m)


@wp.kernel
def max_of_partials_kernel(max_in: wp.array2d(dtype=wp.float32), counts_in: wp.array3d(dtype=wp.int32),
                           min_nis_in: wp.array2d(dtype=wp.float32), stats: wp.array2d(dtype=wp.float64)):
    """One thread per (b): :func:`max_of_partials`."""
    b = wp.tid()
    max_of_partials(b, max_in, counts_in, min_nis_in, stats)



@wp.func
def pair_products(d: wp.vec3d) -> wp.vec3d:
    """(d0 d1, d0 d2, d1 d2): the off-diagonal products of a second moment."""
    return wp.vec3d(d[0] * d[1], d[0] * d[2], d[1] * d[2])


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
def weighted_cov(s: wp.float64, m1: wp.vec3d, m2: wp.vec3d, m3: wp.vec3d) -> wp.mat33d:
    """Covariance from Σw, Σw d, Σw d∘d, Σw (d0d1, d0d2, d1d2)."""
    mean = m1 / s
    xy = m3[0] / s - mean[0] * mean[1]
    xz = m3[1] / s - mean[0] * mean[2]
    yz = m3[2] / s - mean[1] * mean[2]
    return wp.mat33d(m2[0] / s - mean[0] * mean[0], xy, xz,
                     xy, m2[1] / s - mean[1] * mean[1], yz,
                     xz, yz, m2[2] / s - mean[2] * mean[2])


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
    the kernel factor ``kernel_chol[b] = h · ST_JITTER · chol(Σ̂)`` the altimeter scores with, and the decision to
    resample: when ESS < threshold · n, or when exponent remains (between tempering stages)."""
    if stats[b, ST_ACTIVE] == wp.float64(0.0):
        return
    part = chunk_vec()
    for k in range(lane, N_CHUNKS, wp.block_dim()):
        for a in range(N_CHUNK_SUMS):
            part[a] += sums_in[b, k, a]
    tot = wp.tile_sum(wp.tile(part, preserve_type=True))[0]
    if lane != 0:
        return
    s1 = tot[0]
    ess = s1 * s1 / tot[1]
    stats[b, ST_ESS] = ess
    stats[b, ST_LOGNORM] = stats[b, ST_MAX] + wp.log(s1)
    m1 = wp.vec3d(tot[2], tot[3], tot[4])
    for a in range(3):
        stats[b, ST_MEAN_DP + a] = m1[a] / s1
    cov = weighted_cov(s1, m1, wp.vec3d(tot[5], tot[6], tot[7]), wp.vec3d(tot[8], tot[9], tot[10]))
    lo = chol3(cov + wp.float64(1.0e-6) * wp.identity(n=3, dtype=wp.float64))
    stats[b, ST_CHOL + 0] = lo[0, 0]
    stats[b, ST_CHOL + 1] = lo[1, 0]
    stats[b, ST_CHOL + 2] = lo[1, 1]
    stats[b, ST_CHOL + 3] = lo[2, 0]
    stats[b, ST_CHOL + 4] = lo[2, 1]
    stats[b, ST_CHOL + 5] = lo[2, 2]
    stats[b, ST_NIS] = tot[11] / s1
    # JITTER_NIS: tr(h² Σ̂ Ī_p) with Σ̂ = L Lᵀ (its horizontal block)
    ip = wp.vec3d(tot[18], tot[19], tot[20]) / s1
    q = wp.float64(params.bandwidth * params.bandwidth) * (cov[0, 0] * ip[0] + cov[1, 1] * ip[1]
                                                           + wp.float64(2.0) * cov[0, 1] * ip[2])
    stats[b, ST_JITTER] = wp.float64(1.0)
    if q > wp.float64(JITTER_NIS):
        stats[b, ST_JITTER] = wp.sqrt(wp.float64(JITTER_NIS) / q)
    kernel_chol[b] = wp.float32(wp.float64(params.bandwidth) * stats[b, ST_JITTER]) * stats_chol(stats, b)
    for a in range(6):
        stats[b, ST_LAM + a] = tot[12 + a] / s1
    if ess < wp.float64(params.resample_threshold) * wp.float64(n_per) or stats[b, ST_REMAIN] > wp.float64(0.0):
        stats[b, ST_RESAMPLE] = wp.float64(1.0)
        stats[b, ST_RESAMPLES] = stats[b, ST_RESAMPLES] + wp.float64(1.0)


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
def sym_from(stats: wp.array2d(dtype=wp.float64), b: int, col: int) -> wp.mat33d:
    """The symmetric 3×3 matrix stored as six columns (00 11 22 01 02 12) from ``col``."""
    xy = stats[b, col + 3]
    xz = stats[b, col + 4]
    yz = stats[b, col + 5]
    return wp.mat33d(stats[b, col], xy, xz, xy, stats[b, col + 1], yz, xz, yz, stats[b, col + 2])


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
    """The Kalman measurement update of each particle's linear states (SPEC §6b), in the stage that applies the
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
def stats_chol(stats: wp.array2d(dtype=wp.float64), b: int) -> wp.mat33:
    z = wp.float32(0.0)
    return wp.mat33(wp.float32(stats[b, ST_CHOL]), z, z,
                    wp.float32(stats[b, ST_CHOL + 1]), wp.float32(stats[b, ST_CHOL + 2]), z,
                    wp.float32(stats[b, ST_CHOL + 3]), wp.float32(stats[b, ST_CHOL + 4]),
                    wp.float32(stats[b, ST_CHOL + 5]))


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
    """Slot i takes its ancestor in a resampling filter, with uniform weights and the regularisation jitter with
    (partial) kernel shrinkage (Liu & West 2001): ``dp = a dp_anc + (1 - a) m + h chol(Σ̂) z``,
    ``a = sqrt(1 - s h²)``, ``h`` the bandwidth times the stage's ``ST_JITTER`` (:data:`JITTER_NIS`), Σ̂ and m the
    weighted covariance and mean of dp before resampling (stream
    ``stage · 2n + n + j``): the mean is kept and the covariance grows by ``1 + (1 - s) h²``.
    The Kalman mean is the ancestor's (see :mod:`warptan.filter.mpf`). Other filters copy."""
    b = i // n_per
    a = ancestors[i]
    d = dp_in[a]
    lw = logw_in[a]
    if stats[b, ST_RESAMPLE] != wp.float64(0.0):
        lw = -wp.log(float(n_per))
        h = params.bandwidth * wp.float32(stats[b, ST_JITTER])
        if h > 0.0:
            state = wp.rand_init(seeds[b], stage * 2 * n_per + n_per + i % n_per)
            shrink = wp.sqrt(wp.max(1.0 - params.shrinkage * h * h, 0.0))
            mean = wp.vec3(wp.float32(stats[b, ST_MEAN_DP]), wp.float32(stats[b, ST_MEAN_DP + 1]),
                           wp.float32(stats[b, ST_MEAN_DP + 2]))
            d = shrink * d + (1.0 - shrink) * mean + h * (stats_chol(stats, b) * gaussian3(state))
    dp_out[i] = d
    lin_out[i] = lin_in[a]
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



STAGE_BLOCK_DIM = 64
"""Threads of the block that runs one filter's tempering stage on CUDA (:data:`stage_block_kernel`): one lane per
chunk (``N_CHUNKS``), so the weight statistics' block sum is the one :data:`weight_stats_kernel` makes (the same
bits as the separate kernels)."""
RESAMPLE_BLOCK_DIM = 256
"""Threads of the block that resamples one filter on CUDA (:data:`resample_block_kernel`): a particle or two each
(each ancestor is a binary search of dependent loads)."""


@wp.kernel
def stage_block_kernel(
    n_per: int,
    stage: int,
    last_stage: int,
    params: UpdateParams,
    loglik: wp.array(dtype=wp.float32),
    n_valid: wp.array(dtype=wp.int32),
    meta: wp.array2d(dtype=wp.float32),
    nis: wp.array(dtype=wp.float32),
    dp: wp.array(dtype=wp.vec3),
    lam: wp.array(dtype=wp.mat33),
    info: wp.array(dtype=wp.vec3),
    with_ip: int,
    info_pos: wp.array(dtype=wp.vec3),
    kalman: int,
    feedback: wp.array2d(dtype=wp.float64),
    p_col: wp.array2d(dtype=wp.mat33),
    partials: wp.array4d(dtype=wp.float64),
    unpred: wp.array2d(dtype=wp.float64),
    ess: wp.array2d(dtype=wp.float64),
    chunk_max: wp.array2d(dtype=wp.float32),
    chunk_counts: wp.array3d(dtype=wp.int32),
    chunk_min_nis: wp.array2d(dtype=wp.float32),
    chunk_sums: wp.array3d(dtype=wp.float64),
    logw: wp.array(dtype=wp.float32),
    stats: wp.array2d(dtype=wp.float64),
    kernel_chol: wp.array(dtype=wp.mat33),
    lin: wp.array(dtype=vec12),
):
    """One tempering stage of filter b after :data:`temper_partials_kernel`, in one CUDA block (``wp.launch_tiled``,
    :data:`STAGE_BLOCK_DIM` lanes): the pieces of :data:`temper_ess_kernel`, :data:`temper_select_kernel`,
    :data:`add_loglik_partials_kernel`, :data:`max_of_partials_kernel`, :data:`exp_partials_kernel`,
    :data:`weight_stats_kernel`, :data:`normalize_weights_kernel` and (``kalman``) :data:`kalman_update_kernel`, in
    that order, the block's lanes sharing each one's threads with a barrier between them: the same functions on the
    same values (the same bits) in one launch instead of eight, each of which cost a graph node's few µs for a few
    hundred particles. The candidates' partials stay a launch of their own: 1 280 float64 log-sum-exp streams a
    filter, which 64 lanes would run 20 deep."""
    b, lane = wp.tid()
    bd = wp.block_dim()
    for g in range(lane, N_TEMPER, bd):
        temper_ess_of(b, g, partials, ess)
    block_sync()
    if lane == 0:
        temper_select(b, n_per, stage, last_stage, params, meta, ess, unpred, stats)
    block_sync()
    for c in range(lane, N_CHUNKS, bd):
        add_loglik_partial(b, c, n_per, loglik, n_valid, meta, stats, nis, logw, chunk_max, chunk_counts,
                           chunk_min_nis)
    block_sync()
    if lane == 0:
        max_of_partials(b, chunk_max, chunk_counts, chunk_min_nis, stats)
    block_sync()
    for c in range(lane, N_CHUNKS, bd):
        exp_partial(b, c, n_per, logw, dp, nis, lam, with_ip, info_pos, stats, chunk_sums)
    block_sync()
    weight_stats(b, lane, n_per, params, chunk_sums, stats, kernel_chol)
    block_sync()
    for k in range(lane, n_per, bd):
        i = b * n_per + k
        normalize_weight(i, n_per, stats, logw)
        if kalman != 0:
            kalman_update(i, n_per, params, stats, feedback, p_col, lam, info, lin)


@wp.kernel
def resample_block_kernel(
    n_per: int,
    stage: int,
    seeds: wp.array(dtype=wp.int32),
    scheme: int,
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    cdf_sums: wp.array2d(dtype=wp.float64),
    cdf: wp.array(dtype=wp.float32),
    ancestors: wp.array(dtype=wp.int32),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
    logw: wp.array(dtype=wp.float32),
    dp_spare: wp.array(dtype=wp.vec3),
    lin_spare: wp.array(dtype=vec12),
    logw_spare: wp.array(dtype=wp.float32),
):
    """Resampling of filter b in one CUDA block (:data:`RESAMPLE_BLOCK_DIM` lanes): :data:`cdf_partials_kernel`,
    :data:`cdf_kernel`, :data:`ancestors_kernel`, :data:`gather_kernel` (into the spare arrays) and
    :data:`copy_particles_kernel` (back), a barrier between them; the same bits in one launch instead of five."""
    b, lane = wp.tid()
    bd = wp.block_dim()
    for c in range(lane, N_CHUNKS, bd):
        cdf_partial(b, c, n_per, logw, stats, cdf_sums)
    block_sync()
    for c in range(lane, N_CHUNKS, bd):
        cdf_chunk(b, c, n_per, logw, stats, cdf_sums, cdf)
    block_sync()
    for k in range(lane, n_per, bd):
        ancestor(b * n_per + k, n_per, stage, seeds, scheme, stats, cdf, ancestors)
    block_sync()
    for k in range(lane, n_per, bd):
        gather(b * n_per + k, n_per, stage, seeds, params, stats, ancestors, dp, lin, logw, dp_spare, lin_spare,
               logw_spare)
    block_sync()
    for k in range(lane, n_per, bd):
        copy_particle(b * n_per + k, dp_spare, lin_spare, logw_spare, dp, lin, logw)


@wp.kernel
def gather_modes_kernel(ancestors: wp.array(dtype=wp.int32), mean_in: wp.array(dtype=modes_vec),
                        post_in: wp.array(dtype=modes_vec), mean_out: wp.array(dtype=modes_vec),
                        post_out: wp.array(dtype=modes_vec)):
    """Slot i takes its ancestor's map-error mode amplitudes: the prior it was weighted with and its posterior (the
    map error under a hypothesis belongs to the hypothesis)."""
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
def modes_finalize_kernel(
    n_per: int,
    m: int,
    table: wp.array(dtype=modes_vec),
    stats: wp.array2d(dtype=wp.float64),
    post: wp.array(dtype=modes_vec),
    var: wp.array(dtype=modes_vec),
    mean: wp.array(dtype=modes_vec),
):
    """After an update (and a re-spread): each particle's map-error mode amplitudes for the next scan. Applied: the
    model's ``ρ_i q_i`` (:func:`warptan.kernels.likelihood.mode_post`); skipped: the prediction alone (``μ ← ρ T
    μ``); re-spread: zero. Before :func:`modes_variance_kernel` (it reads the filter's variances unchanged)."""
    i = wp.tid()
    b = i // n_per
    if stats[b, ST_RESPREAD] != wp.float64(0.0):
        mean[i] = modes_vec()
    elif stats[b, ST_SKIP] != wp.float64(0.0):
        mu, _pv = mode_prior(table, m, mean[i], var[b])
        mean[i] = wp.cw_mul(table[m + MODE_RHO], mu)
    else:
        mean[i] = post[i]


@wp.kernel
def modes_variance_kernel(m: int, table: wp.array(dtype=modes_vec), stats: wp.array2d(dtype=wp.float64),
                          var: wp.array(dtype=modes_vec)):
    """Filter b's variances of its mode amplitudes for the next scan: applied, ``P_i ← ρ_i² P⁻_i / (1 + P⁻_i) + (1 −
    ρ_i²) k⁰_i`` (the Kalman update of independent modes of unit noise, then a first-order step along the track);
    skipped, the step alone; re-spread (or none yet and skipped): none (negative: the next scan starts from the
    one-scan prior ``k⁰``)."""
    b = wp.tid()
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


@wp.func
def integrity_step(b: int, params: UpdateParams, stats: wp.array2d(dtype=wp.float64),
                   integrity: wp.array2d(dtype=wp.float64), kernel_chol: wp.array(dtype=wp.mat33)):
    """One thread per filter, after the last stage (MBARI TRN style): the mean over the last ``integrity_window``
    informative updates of the smallest NIS of any particle — large only when no hypothesis explains the scan,
    whereas a wide but healthy cloud (acquisition, a flat likelihood) still holds particles that do; above
    ``integrity_threshold`` (after ``integrity_min_updates``
    informative updates, so that acquisition is not judged) the filter is lost: flag it for a re-spread and
    restart the window."""
    if stats[b, ST_SKIP] != wp.float64(0.0):
        return
    w = params.integrity_window
    k = int(integrity[b, IN_SINCE])
    integrity[b, IN_RING + k % w] = stats[b, ST_NIS_MIN]
    k += 1
    count = wp.min(k, w)
    total = wp.float64(0.0)
    for j in range(count):
        total += integrity[b, IN_RING + j]
    mean = total / wp.float64(count)
    integrity[b, IN_MEAN] = mean
    if k >= params.integrity_min_updates and mean > wp.float64(params.integrity_threshold):
        stats[b, ST_RESPREAD] = wp.float64(1.0)
        kernel_chol[b] = params.bandwidth * params.respread_chol  # the re-spread cloud's kernel
        integrity[b, IN_RESPREADS] = integrity[b, IN_RESPREADS] + wp.float64(1.0)
        k = 0
    integrity[b, IN_SINCE] = wp.float64(k)


@wp.kernel
def integrity_kernel(params: UpdateParams, stats: wp.array2d(dtype=wp.float64),
                     integrity: wp.array2d(dtype=wp.float64), kernel_chol: wp.array(dtype=wp.mat33)):
    """One thread per (b): :func:`integrity_step`."""
    b = wp.tid()
    integrity_step(b, params, stats, integrity, kernel_chol)



@wp.func
def respread_particle(
    i: int,
    n_per: int,
    offset: int,
    seeds: wp.array(dtype=wp.int32),
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    dp: wp.array(dtype=wp.vec3),
    logw: wp.array(dtype=wp.float32),
):
    """A filter flagged lost re-spreads dp around its weighted mean with the re-spread covariance, uniform
    weights (Kalman means kept); stream ``offset + j``."""
    b = i // n_per
    if stats[b, ST_RESPREAD] == wp.float64(0.0):
        return
    state = wp.rand_init(seeds[b], offset + i % n_per)
    centre = wp.vec3(wp.float32(stats[b, ST_MEAN_DP]), wp.float32(stats[b, ST_MEAN_DP + 1]),
                     wp.float32(stats[b, ST_MEAN_DP + 2]))
    dp[i] = centre + params.respread_chol * gaussian3(state)
    logw[i] = -wp.log(float(n_per))


@wp.kernel
def respread_kernel(
    n_per: int,
    offset: int,
    seeds: wp.array(dtype=wp.int32),
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    dp: wp.array(dtype=wp.vec3),
    logw: wp.array(dtype=wp.float32),
):
    """One thread per (i): :func:`respread_particle`."""
    i = wp.tid()
    respread_particle(i, n_per, offset, seeds, params, stats, dp, logw)



@wp.func
def summary_partial(b: int, c: int, n_per: int, logw: wp.array(dtype=wp.float32), dp: wp.array(dtype=wp.vec3),
                    lin: wp.array(dtype=vec12), partial_out: wp.array3d(dtype=wp.float64)):
    """Filter b, chunk c, after the update (``N_SUMMARY_SUMS`` values): Σw, Σw dp (3), Σw dp∘dp (3),
    Σw (xy, xz, yz), Σw l (12), Σw l∘l (12)."""
    lo, hi = chunk_range(c, n_per)
    s = wp.float64(0.0)
    m1 = wp.vec3d()
    m2 = wp.vec3d()
    m3 = wp.vec3d()
    l1 = wp.vector(length=12, dtype=wp.float64)
    l2 = wp.vector(length=12, dtype=wp.float64)
    for k in range(lo, hi):
        i = b * n_per + k
        w = wp.float64(wp.exp(logw[i]))
        d = wp.vec3d(dp[i])
        s += w
        m1 += w * d
        m2 += w * wp.cw_mul(d, d)
        m3 += w * pair_products(d)
        lm = lin[i]
        for a in range(12):
            x = wp.float64(lm[a])
            l1[a] += w * x
            l2[a] += w * x * x
    partial_out[b, c, 0] = s
    for a in range(3):
        partial_out[b, c, 1 + a] = m1[a]
        partial_out[b, c, 4 + a] = m2[a]
        partial_out[b, c, 7 + a] = m3[a]
    for a in range(12):
        partial_out[b, c, 10 + a] = l1[a]
        partial_out[b, c, 22 + a] = l2[a]


@wp.kernel
def summary_partials_kernel(n_per: int, logw: wp.array(dtype=wp.float32), dp: wp.array(dtype=wp.vec3),
                            lin: wp.array(dtype=vec12), partial_out: wp.array3d(dtype=wp.float64)):
    """One thread per (b, c): :func:`summary_partial`."""
    b, c = wp.tid()
    summary_partial(b, c, n_per, logw, dp, lin, partial_out)



@wp.func
def record_summary(
    b: int,
    lane: int,
    params: UpdateParams,
    partial_in: wp.array3d(dtype=wp.float64),
    stats: wp.array2d(dtype=wp.float64),
    integrity: wp.array2d(dtype=wp.float64),
    slot: wp.array(dtype=wp.int32),
    history: wp.array3d(dtype=wp.float64),
    feedback: wp.array2d(dtype=wp.float64),
):
    """One block per filter (``wp.launch_tiled``, lanes over the chunks): the update's record in
    ``history[slot[0], b]`` (``H_*`` columns) and ``feedback[b]`` (``FB_*`` columns: what the covariance update and
    the closed loop read)."""
    part = summary_vec()
    for c in range(lane, N_CHUNKS, wp.block_dim()):
        for a in range(34):
            part[a] += partial_in[b, c, a]
    tot = wp.tile_sum(wp.tile(part, preserve_type=True))[0]
    if lane != 0:
        return
    s = tot[0]
    applied = stats[b, ST_APPLIED]
    if stats[b, ST_SKIP] != wp.float64(0.0):
        applied = wp.float64(0.0)
    feedback[b, FB_APPLIED] = applied
    gate = wp.float64(1.0)  # the verdict the particles' Kalman update read (the previous update's), not yet renewed
    if params.gate_linear != 0:
        gate = feedback[b, FB_CONVERGED]
    for a in range(6):
        feedback[b, FB_LAM + a] = gate * applied * stats[b, ST_LAM + a]
    for a in range(3):
        feedback[b, FB_MEAN_DP + a] = tot[1 + a] / s
    for a in range(12):
        feedback[b, FB_MEAN_L + a] = tot[10 + a] / s
    judged = integrity[b, IN_SINCE] >= wp.float64(params.integrity_min_updates)
    ok = integrity[b, IN_MEAN] <= wp.float64(params.integrity_threshold) and stats[b, ST_RESPREAD] == wp.float64(0.0)
    feedback[b, FB_CONVERGED] = wp.where(judged and ok, wp.float64(1.0), wp.float64(0.0))
    t = slot[0]
    if t >= history.shape[0]:
        return
    cov = weighted_cov(s, wp.vec3d(tot[1], tot[2], tot[3]), wp.vec3d(tot[4], tot[5], tot[6]),
                       wp.vec3d(tot[7], tot[8], tot[9]))
    history[t, b, H_ESS] = stats[b, ST_ESS]
    history[t, b, H_RESAMPLES] = stats[b, ST_RESAMPLES]
    history[t, b, H_RESPREAD] = stats[b, ST_RESPREAD]
    history[t, b, H_BAD] = stats[b, ST_BAD]
    history[t, b, H_UNPREDICTABLE] = stats[b, ST_UNPREDICTABLE]
    history[t, b, H_SUM_W] = s
    for a in range(3):
        history[t, b, H_MEAN_DP + a] = tot[1 + a] / s
        history[t, b, H_COV_DP + a] = cov[a, a]
    history[t, b, H_COV_DP + 3] = cov[0, 1]
    history[t, b, H_COV_DP + 4] = cov[0, 2]
    history[t, b, H_COV_DP + 5] = cov[1, 2]
    history[t, b, H_STAGES] = stats[b, ST_STAGES]
    history[t, b, H_NIS] = stats[b, ST_NIS_MIN]
    history[t, b, H_NIS_POST] = stats[b, ST_NIS]
    history[t, b, H_NIS_AVG] = integrity[b, IN_MEAN]
    history[t, b, H_SKIPPED] = stats[b, ST_SKIP]
    history[t, b, H_APPLIED] = stats[b, ST_APPLIED]
    for a in range(12):
        mean = tot[10 + a] / s
        history[t, b, H_MEAN_L + a] = mean
        history[t, b, H_VAR_L + a] = wp.max(tot[22 + a] / s - mean * mean, wp.float64(0.0))


@wp.kernel
def summary_kernel(params: UpdateParams, partial_in: wp.array3d(dtype=wp.float64), stats: wp.array2d(dtype=wp.float64),
                   integrity: wp.array2d(dtype=wp.float64), slot: wp.array(dtype=wp.int32),
                   history: wp.array3d(dtype=wp.float64), feedback: wp.array2d(dtype=wp.float64)):
    """One thread per (b, lane): :func:`record_summary`."""
    b, lane = wp.tid()
    record_summary(b, lane, params, partial_in, stats, integrity, slot, history, feedback)



@wp.func
def update_covariance(
    b: int,
    measurement_update: int,
    closed_loop: int,
    feedback: wp.array2d(dtype=wp.float64),
    slot: wp.array(dtype=wp.int32),
    cov: wp.array3d(dtype=wp.mat33d),
    pos: wp.array(dtype=wp.vec3d),
    vel: wp.array(dtype=wp.vec3d),
    quat: wp.array(dtype=wp.vec4d),
    accel_bias: wp.array(dtype=wp.vec3d),
    gyro_bias: wp.array(dtype=wp.vec3d),
    injections: wp.array(dtype=wp.int32),
    nominal_hist: wp.array3d(dtype=wp.float64),
    p_hist: wp.array3d(dtype=wp.float64),
):
    """One thread per filter, after the update's record (float64, on the filter's device):

    1. the nominal INS at this update into ``nominal_hist[slot, b]`` (p, v, q, b_a, b_g: before any injection);
    2. the Kalman measurement update of the shared P (``measurement_update``): ``P⁺ = P - P_:θ Λ̄ (I + A Λ̄)⁻¹ P_θ:``
       (A = P_θθ, Λ̄ = ``feedback`` FB_LAM, the weighted mean attitude information times the exponent applied);
       its diagonal into ``p_hist[slot, b]``;
    3. closed loop (``closed_loop``, filters the integrity monitor judges consistent, FB_CONVERGED): nominal ⊕ the
       mean error (position, velocity, attitude ``q ⊗ Exp(θ̂)``, biases), ``P <- G P Gᵀ``,
       ``G = diag(I, I - [θ̂/2]×, I, I)`` (Solà 2017 §6.3), ``injections[b] += 1``; :func:`reset_kernel` then
       re-expresses the particles."""
    t = slot[0]
    record = t < nominal_hist.shape[0]
    if record:
        for a in range(3):
            nominal_hist[t, b, NOM_POS + a] = pos[b][a]
            nominal_hist[t, b, NOM_VEL + a] = vel[b][a]
            nominal_hist[t, b, NOM_BA + a] = accel_bias[b][a]
            nominal_hist[t, b, NOM_BG + a] = gyro_bias[b][a]
        for a in range(4):
            nominal_hist[t, b, NOM_QUAT + a] = quat[b][a]
    if measurement_update != 0:
        lam = sym_from(feedback, b, FB_LAM)
        gain = lam * wp.inverse(wp.identity(n=3, dtype=wp.float64) + cov[b, 1, 1] * lam)
        c0 = cov[b, 0, 1]
        c1 = cov[b, 1, 1]
        c2 = cov[b, 2, 1]
        c3 = cov[b, 3, 1]
        for r in range(4):
            lg = block_of(r, c0, c1, c2, c3, c3) * gain  # P_:θ's blocks, read before any is overwritten
            for c in range(4):
                cov[b, r, c] = cov[b, r, c] - lg * wp.transpose(block_of(c, c0, c1, c2, c3, c3))
        half = wp.float64(0.5)
        for r in range(4):
            for c in range(r, 4):
                m = half * (cov[b, r, c] + wp.transpose(cov[b, c, r]))
                cov[b, r, c] = m
                cov[b, c, r] = wp.transpose(m)
    if record:
        for r in range(4):
            blk = cov[b, r, r]
            for a in range(3):
                p_hist[t, b, 3 * r + a] = blk[a, a]
    if closed_loop == 0 or feedback[b, FB_CONVERGED] == wp.float64(0.0):
        return
    l_hat = wp.vector(length=12, dtype=wp.float64)
    for a in range(12):
        l_hat[a] = feedback[b, FB_MEAN_L + a]
    th = wp.vec3d(l_hat[3], l_hat[4], l_hat[5])
    pos[b] = pos[b] + wp.vec3d(feedback[b, FB_MEAN_DP], feedback[b, FB_MEAN_DP + 1], feedback[b, FB_MEAN_DP + 2])
    vel[b] = vel[b] + wp.vec3d(l_hat[0], l_hat[1], l_hat[2])
    quat[b] = quat_mul_exp_d(quat[b], th)
    accel_bias[b] = accel_bias[b] + wp.vec3d(l_hat[6], l_hat[7], l_hat[8])
    gyro_bias[b] = gyro_bias[b] + wp.vec3d(l_hat[9], l_hat[10], l_hat[11])
    g = wp.identity(n=3, dtype=wp.float64) - wp.float64(0.5) * skew_d(th)
    for c in range(4):
        cov[b, 1, c] = g * cov[b, 1, c]
    for r in range(4):
        cov[b, r, 1] = cov[b, r, 1] * wp.transpose(g)
    injections[b] = injections[b] + 1


@wp.kernel
def covariance_update_kernel(
    measurement_update: int,
    closed_loop: int,
    feedback: wp.array2d(dtype=wp.float64),
    slot: wp.array(dtype=wp.int32),
    cov: wp.array3d(dtype=wp.mat33d),
    pos: wp.array(dtype=wp.vec3d),
    vel: wp.array(dtype=wp.vec3d),
    quat: wp.array(dtype=wp.vec4d),
    accel_bias: wp.array(dtype=wp.vec3d),
    gyro_bias: wp.array(dtype=wp.vec3d),
    injections: wp.array(dtype=wp.int32),
    nominal_hist: wp.array3d(dtype=wp.float64),
    p_hist: wp.array3d(dtype=wp.float64),
):
    """One thread per (b): :func:`update_covariance`."""
    b = wp.tid()
    update_covariance(b, measurement_update, closed_loop, feedback, slot, cov, pos, vel, quat, accel_bias, gyro_bias,
                      injections, nominal_hist, p_hist)



@wp.func
def reset_particle(
    i: int,
    n_per: int,
    feedback: wp.array2d(dtype=wp.float64),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
):
    """Closed loop: :func:`covariance_update_kernel` injected the filter's mean error ``[d̂p, d̂v, θ̂, d̂ba, d̂bg]``
    (``feedback``) into its nominal INS; every particle's error is taken relative to the new nominal, so that each
    particle's total state is unchanged: additive parts minus the mean, the attitude
    ``dθ_i <- Log(Exp(θ̂)⁻¹ Exp(dθ_i))`` (right perturbations, SPEC §3). Filters not injected (FB_CONVERGED = 0)
    are left alone."""
    b = i // n_per
    if feedback[b, FB_CONVERGED] == wp.float64(0.0):
        return
    m = vec12()
    for a in range(12):
        m[a] = wp.float32(feedback[b, FB_MEAN_L + a])
    dp[i] = dp[i] - wp.vec3(wp.float32(feedback[b, FB_MEAN_DP]), wp.float32(feedback[b, FB_MEAN_DP + 1]),
                            wp.float32(feedback[b, FB_MEAN_DP + 2]))
    lm = lin[i]
    th_hat = wp.vec3(m[3], m[4], m[5])
    th = wp.vec3(lm[3], lm[4], lm[5])
    rel = quat_log_wxyz(quat_mul_wxyz(quat_exp_wxyz(-th_hat), quat_exp_wxyz(th)))
    out = lm - m
    out[3] = rel[0]
    out[4] = rel[1]
    out[5] = rel[2]
    lin[i] = out


@wp.kernel
def reset_kernel(
    n_per: int,
    feedback: wp.array2d(dtype=wp.float64),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
):
    """One thread per (i): :func:`reset_particle`."""
    i = wp.tid()
    reset_particle(i, n_per, feedback, dp, lin)



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
        partial_out[b, c, MOM_W] += w
        for a in range(3):
            partial_out[b, c, MOM_DP + a] += w * wp.float64(d[a])
            for e in range(3):
                partial_out[b, c, MOM_DPDP + 3 * a + e] += w * wp.float64(d[a]) * wp.float64(d[e])
        for a in range(12):
            partial_out[b, c, MOM_L + a] += w * wp.float64(lm[a])
            for e in range(12):
                partial_out[b, c, MOM_LL + 12 * a + e] += w * wp.float64(lm[a]) * wp.float64(lm[e])


@wp.kernel
def combine_partials_kernel(partial_in: wp.array3d(dtype=wp.float64), total_out: wp.array2d(dtype=wp.float64)):
    """One thread per (filter, moment): sum the chunks in order."""
    b, k = wp.tid()
    s = wp.float64(0.0)
    for c in range(partial_in.shape[1]):
        s += partial_in[b, c, k]
    total_out[b, k] = s


@wp.kernel
def move_pose_kernel(
    n_per: int,
    seeds: wp.array(dtype=wp.int32),
    phi: wp.array3d(dtype=wp.mat33),
    chol: wp.array3d(dtype=wp.mat33),
    pose: wp.array2d(dtype=wp.float64),
    exponent: wp.array(dtype=wp.float32),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
    pos_out: wp.array(dtype=wp.vec3),
    quat_out: wp.array(dtype=wp.vec4),
    stats: wp.array2d(dtype=wp.float64),
):
    """The head of an update on CUDA, one thread per particle: :func:`move_particle` (the interval), then
    :func:`pose_of_particle` (its pose for the model), and the first particle of each filter :func:`begin_stats` (no
    model reads the statistics): :data:`time_update_kernel`, :data:`particle_poses_kernel` and
    :data:`begin_update_kernel` in one launch, the same bits."""
    i = wp.tid()
    move_particle(i, 0, n_per, seeds, phi, chol, dp, lin)
    pose_of_particle(i, n_per, pose, dp, lin, pos_out, quat_out)
    if i % n_per == 0:
        begin_stats(i // n_per, exponent, stats)


@wp.kernel
def integrity_block_kernel(
    n_per: int,
    offset: int,
    seeds: wp.array(dtype=wp.int32),
    params: UpdateParams,
    stats: wp.array2d(dtype=wp.float64),
    integrity: wp.array2d(dtype=wp.float64),
    kernel_chol: wp.array(dtype=wp.mat33),
    dp: wp.array(dtype=wp.vec3),
    logw: wp.array(dtype=wp.float32),
):
    """The integrity monitor of filter b in one CUDA block (:data:`STAGE_BLOCK_DIM` lanes): :func:`integrity_step`
    (lane 0), a barrier, :func:`respread_particle` (:data:`integrity_kernel` + :data:`respread_kernel`, the same
    bits)."""
    b, lane = wp.tid()
    if lane == 0:
        integrity_step(b, params, stats, integrity, kernel_chol)
    block_sync()
    for k in range(lane, n_per, wp.block_dim()):
        respread_particle(b * n_per + k, n_per, offset, seeds, params, stats, dp, logw)


@wp.kernel
def record_block_kernel(
    n_per: int,
    params: UpdateParams,
    measurement_update: int,
    closed_loop: int,
    logw: wp.array(dtype=wp.float32),
    stats: wp.array2d(dtype=wp.float64),
    integrity: wp.array2d(dtype=wp.float64),
    slot: wp.array(dtype=wp.int32),
    summary_sums: wp.array3d(dtype=wp.float64),
    history: wp.array3d(dtype=wp.float64),
    feedback: wp.array2d(dtype=wp.float64),
    cov: wp.array3d(dtype=wp.mat33d),
    pos: wp.array(dtype=wp.vec3d),
    vel: wp.array(dtype=wp.vec3d),
    quat: wp.array(dtype=wp.vec4d),
    accel_bias: wp.array(dtype=wp.vec3d),
    gyro_bias: wp.array(dtype=wp.vec3d),
    injections: wp.array(dtype=wp.int32),
    nominal_hist: wp.array3d(dtype=wp.float64),
    p_hist: wp.array3d(dtype=wp.float64),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
):
    """The record and feedback of filter b in one CUDA block (:data:`STAGE_BLOCK_DIM` lanes, so the block sum is
    :data:`summary_kernel`'s): :func:`summary_partial` (lane per chunk), :func:`record_summary`,
    :func:`update_covariance` (lane 0) and in closed loop :func:`reset_particle`, barriers between
    (:data:`summary_partials_kernel`, :data:`summary_kernel`, :data:`covariance_update_kernel`,
    :data:`reset_kernel`: the same bits). The slot advances after, in a launch of its own (every filter reads it)."""
    b, lane = wp.tid()
    bd = wp.block_dim()
    for c in range(lane, N_CHUNKS, bd):
        summary_partial(b, c, n_per, logw, dp, lin, summary_sums)
    block_sync()
    record_summary(b, lane, params, summary_sums, stats, integrity, slot, history, feedback)
    block_sync()
    if lane == 0:
        update_covariance(b, measurement_update, closed_loop, feedback, slot, cov, pos, vel, quat, accel_bias,
                          gyro_bias, injections, nominal_hist, p_hist)
    block_sync()
    if closed_loop != 0:
        for k in range(lane, n_per, bd):
            reset_particle(b * n_per + k, n_per, feedback, dp, lin)
