"""CUDA forms that run a filter's pieces as one block (the same functions, the same bits): a tempering stage, a
resampling, the update's head and tail."""

import warp as wp

from warptan.kernels.block import block_sync, on_cuda
from warptan.kernels.filter.common import (
    N_CHUNKS,
    N_TEMPER,
    ST_REMAIN,
    ST_RESAMPLE,
    ST_RESPREAD,
    WARP_LANES,
    UpdateParams,
    vec12,
)
from warptan.kernels.filter.integrity import integrity_step, respread_particle
from warptan.kernels.filter.moves import move_particle, nominal_pose, pose_at, pose_of_particle
from warptan.kernels.filter.record import (
    end_update,
    record_summary,
    reset_particle,
    summary_partial,
    update_covariance_lanes,
)
from warptan.kernels.filter.resampling import (
    ancestor,
    cdf_chunk,
    cdf_partial,
    copy_particle,
    gather,
    gathered,
    modes_finalize,
    modes_variance,
)
from warptan.kernels.filter.tempering import begin_stats, temper_ess_lanes, temper_search, temper_select
from warptan.kernels.filter.weights import (
    add_loglik_partial,
    exp_partial,
    kalman_update,
    max_of_partials,
    normalize_weight,
    weight_stats,
)
from warptan.kernels.likelihood import modes_vec

wp.set_module_options({"enable_backward": False})

STAGE_BLOCK_DIM = 512
"""Threads of the block that runs one filter's tempering stage and its resampling on CUDA (:data:`stage_block_kernel`):
a particle each in the resampling for N <= 512, two up to N = 1 024 (each ancestor is a binary search of dependent
loads; a lane's gathered particles wait in registers for the barrier), more through the spare arrays; the per-chunk
pieces take the first ``N_CHUNKS`` lanes and the chunk reductions a warp each
(:func:`~warptan.kernels.filter.common.chunk_sum`, the candidates' ESS a warp per candidate), the same functions as the
separate kernels: the same bits. Measured on an H100 (S8 / S7, N = 500, M = 400): the block's own time (lane-0 clock
stamps) 32.3 / 33.2 µs at 256 lanes, 28.9 / 29.6 µs at 512 (the ancestors' searches, the gather and the copy halve); the
update graph's device time (``scripts/step_timeline.py``, two rounds) at 256, 128 and 64 lanes was 172 / 223, 175 / 226
and 202 / 250 µs. 512 lanes need the register cap (:data:`STAGE_MAX_REGISTERS`): the compiler's 134 registers a thread
do not fit a block of 512."""
STAGE_MAX_REGISTERS = 128
"""Registers a thread of :data:`stage_block_kernel` may hold on CUDA (``__maxnreg__``): 65 536 a multiprocessor over
:data:`STAGE_BLOCK_DIM` = 512 lanes. The bits are those of the uncapped kernel (CUDA digest identical)."""
RECORD_BLOCK_DIM = 64
"""Threads of the block that runs one filter's integrity monitor, map-error modes and record on CUDA
(:data:`record_block_kernel`): one lane per chunk (``N_CHUNKS``); the summary's sum over the chunks is the first warp's,
as in :data:`summary_kernel`."""

TEMPER_BLOCK_DIM = 32
"""CUDA block size of :data:`~warptan.kernels.filter.tempering.temper_partials_kernel`: 1 280 threads a filter, each a
chain of float64 exponentials over its chunk; in blocks of 256 they ran on five multiprocessors (7.2 µs a stage on an
H100, ncu), in blocks of a warp on forty."""
MOVE_BLOCK_DIM = 32
"""CUDA block size of :data:`move_pose_kernel`: a particle's move is a long chain (15 normal draws, 40 3×3 products)
and one filter has a few hundred, so blocks of a warp spread them over 16 multiprocessors instead of two."""


@wp.func
def put_particle(i: int, d: wp.vec3, lm: vec12, lw: float, p_nom: wp.vec3d, q_nom: wp.vec4,
                 dp: wp.array(dtype=wp.vec3), lin: wp.array(dtype=vec12), logw: wp.array(dtype=wp.float32),
                 pos_out: wp.array(dtype=wp.vec3), quat_out: wp.array(dtype=wp.vec4)):
    """Particle i set to (d, lm, lw) and its pose written: :func:`copy_particle` then :func:`pose_of_particle` on
    values already at hand (the nominal pose read before: a load after the stores waits for them)."""
    dp[i] = d
    lin[i] = lm
    logw[i] = lw
    p, q = pose_at(p_nom, q_nom, d, lm)
    pos_out[i] = p
    quat_out[i] = q


@wp.func
def gather_modes_lanes(b: int, lane: int, n_per: int, ancestors: wp.array(dtype=wp.int32),
                       values: wp.array(dtype=modes_vec), spare: wp.array(dtype=modes_vec)):
    """``values[i] ← values[ancestors[i]]`` for filter b's particles over the lanes of its block (every lane must call
    it): up to two a lane wait in registers for the barrier, more go through ``spare`` (the CPU's one-thread block)."""
    bd = wp.block_dim()
    if n_per <= 2 * bd:
        i0 = b * n_per + lane
        i1 = i0 + bd
        v0 = modes_vec()
        v1 = modes_vec()
        if lane < n_per:
            v0 = values[ancestors[i0]]
        if lane + bd < n_per:
            v1 = values[ancestors[i1]]
        block_sync()
        if lane < n_per:
            values[i0] = v0
        if lane + bd < n_per:
            values[i1] = v1
    else:
        for k in range(lane, n_per, bd):
            spare[b * n_per + k] = values[ancestors[b * n_per + k]]
        block_sync()
        for k in range(lane, n_per, bd):
            values[b * n_per + k] = spare[b * n_per + k]


@wp.kernel(cuda_max_registers=STAGE_MAX_REGISTERS)
def stage_block_kernel(
    n_per: int,
    stage: int,
    last_stage: int,
    params: UpdateParams,
    loglik: wp.array(dtype=wp.float32),
    n_valid: wp.array(dtype=wp.int32),
    meta: wp.array2d(dtype=wp.float32),
    nis: wp.array(dtype=wp.float32),
    lam: wp.array(dtype=wp.mat33),
    info: wp.array(dtype=wp.vec3),
    with_ip: int,
    info_pos: wp.array(dtype=wp.vec3),
    kalman: int,
    feedback: wp.array2d(dtype=wp.float64),
    p_col: wp.array2d(dtype=wp.mat33),
    seeds: wp.array(dtype=wp.int32),
    scheme: int,
    pose: wp.array2d(dtype=wp.float64),
    partials: wp.array4d(dtype=wp.float64),
    unpred: wp.array2d(dtype=wp.float64),
    ess: wp.array2d(dtype=wp.float64),
    chunk_max: wp.array2d(dtype=wp.float32),
    chunk_counts: wp.array3d(dtype=wp.int32),
    chunk_min_nis: wp.array2d(dtype=wp.float32),
    chunk_sums: wp.array3d(dtype=wp.float64),
    stats: wp.array2d(dtype=wp.float64),
    kernel_chol: wp.array(dtype=wp.mat33),
    cdf_sums: wp.array2d(dtype=wp.float64),
    cdf: wp.array(dtype=wp.float32),
    ancestors: wp.array(dtype=wp.int32),
    dp: wp.array(dtype=wp.vec3),
    lin: wp.array(dtype=vec12),
    logw: wp.array(dtype=wp.float32),
    dp_spare: wp.array(dtype=wp.vec3),
    lin_spare: wp.array(dtype=vec12),
    logw_spare: wp.array(dtype=wp.float32),
    pos_out: wp.array(dtype=wp.vec3),
    quat_out: wp.array(dtype=wp.vec4),
    with_modes: int,
    mode_mean: wp.array(dtype=modes_vec),
    mode_post: wp.array(dtype=modes_vec),
    mode_mean_spare: wp.array(dtype=modes_vec),
    mode_post_spare: wp.array(dtype=modes_vec),
    more: wp.array(dtype=wp.int32),
):
    """One tempering stage of filter b after :data:`temper_partials_kernel`, and its resampling, in one CUDA block
    (``wp.launch_tiled``, :data:`STAGE_BLOCK_DIM` lanes), the block's lanes sharing each piece's threads with a barrier
    between pieces; on the CPU, where a block is one thread, the whole stage in one launch, the candidates searched
    in order in the block (:func:`~warptan.kernels.filter.tempering.temper_search`, no partials launched before):

    * the stage: :data:`temper_ess_kernel` (CPU: :data:`temper_search_kernel`), :data:`temper_select_kernel`,
      :data:`add_loglik_partials_kernel`, :data:`max_of_partials_kernel`, :data:`exp_partials_kernel`,
      :data:`weight_stats_kernel`, :data:`normalize_weights_kernel` and (``kalman``) :data:`kalman_update_kernel`;
    * the resampling (the filters whose statistics say so; the others keep their particles):
      :data:`cdf_partials_kernel`, :data:`cdf_kernel`, :data:`ancestors_kernel`, :data:`gather_kernel` (into the
      spare arrays), :data:`copy_particles_kernel` (back), and with ``with_modes`` in a filter that resampled
      :data:`gather_modes_kernel` and :data:`copy_modes_kernel` (:func:`gather_modes_lanes`): the modes' prior means,
      and their posteriors only at the filter's last stage (a later stage's model writes every particle's anew; the
      same result);
    * what the next stage would launch before its model: the particles' poses (:data:`particle_poses_kernel`) and,
      when the filter has exponent left, ``more[stage + 1] = 1`` (the next stage's flag; :data:`advance_slot_kernel`
      or the record block clears the flags at the update's end).

    The same functions on the same values, the same bits as the separate kernels, in one graph node instead of
    fifteen (two before the resampling joined it: a node costs ~2 µs whatever its work). The candidates' partials stay
    a launch of their own: 1 280 float64 log-sum-exp streams a filter, which one multiprocessor would run five deep
    (inside this block the stage and resampling took 63 / 50 µs against 51 / 41 µs with them apart, S8 / S7, H100,
    ``scripts/bench_update_pieces.py``)."""
    b, lane = wp.tid()
    bd = wp.block_dim()
    if on_cuda() == 0:  # the CPU (a block is one thread): the candidates in order until one is taken, no launch
        temper_search(b, n_per, stage, params, loglik, n_valid, meta, logw, stats, partials, unpred, ess)
    else:
        for g in range(lane // WARP_LANES, N_TEMPER, wp.max(bd // WARP_LANES, 1)):  # (a warp per candidate)
            temper_ess_lanes(b, g, lane % WARP_LANES, partials, ess)
    block_sync()
    if lane == 0:
        temper_select(b, n_per, stage, last_stage, params, meta, ess, unpred, stats)
    block_sync()
    for c in range(lane, N_CHUNKS, bd):
        add_loglik_partial(b, c, n_per, loglik, n_valid, meta, stats, nis, logw, chunk_max, chunk_counts,
                           chunk_min_nis)
    block_sync()
    if lane < WARP_LANES:
        max_of_partials(b, lane, chunk_max, chunk_counts, chunk_min_nis, stats)
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
    block_sync()
    for c in range(lane, N_CHUNKS, bd):
        cdf_partial(b, c, n_per, logw, stats, cdf_sums)
    block_sync()
    for c in range(lane, N_CHUNKS, bd):
        cdf_chunk(b, c, n_per, logw, stats, cdf_sums, cdf)
    block_sync()
    for k in range(lane, n_per, bd):
        ancestor(b * n_per + k, n_per, stage, seeds, scheme, stats, cdf, ancestors)
    block_sync()
    if n_per <= 2 * bd:  # (CUDA) a lane's two particles wait in registers for the barrier: no spare round trip
        i0 = b * n_per + lane
        i1 = i0 + bd
        p_nom, q_nom = nominal_pose(pose, b)
        d0 = wp.vec3()
        l0 = vec12()
        w0 = float(0.0)
        d1 = wp.vec3()
        l1 = vec12()
        w1 = float(0.0)
        if lane < n_per:
            d0, l0, w0 = gathered(i0, n_per, stage, seeds, params, stats, ancestors, dp, lin, logw)
        if lane + bd < n_per:
            d1, l1, w1 = gathered(i1, n_per, stage, seeds, params, stats, ancestors, dp, lin, logw)
        block_sync()
        if lane < n_per:
            put_particle(i0, d0, l0, w0, p_nom, q_nom, dp, lin, logw, pos_out, quat_out)
        if lane + bd < n_per:
            put_particle(i1, d1, l1, w1, p_nom, q_nom, dp, lin, logw, pos_out, quat_out)
    else:
        for k in range(lane, n_per, bd):
            gather(b * n_per + k, n_per, stage, seeds, params, stats, ancestors, dp, lin, logw, dp_spare, lin_spare,
                   logw_spare)
        block_sync()
        for k in range(lane, n_per, bd):
            copy_particle(b * n_per + k, dp_spare, lin_spare, logw_spare, dp, lin, logw)
            pose_of_particle(b * n_per + k, n_per, pose, dp, lin, pos_out, quat_out)
    if with_modes != 0 and stats[b, ST_RESAMPLE] != wp.float64(0.0):  # (the same for every lane of the block)
        # the modes' prior means follow the particles; their posteriors only at the filter's last stage (a later
        # stage's model writes every particle's anew)
        last = last_stage != 0 or stats[b, ST_REMAIN] <= wp.float64(0.0)
        gather_modes_lanes(b, lane, n_per, ancestors, mode_mean, mode_mean_spare)
        if last:
            gather_modes_lanes(b, lane, n_per, ancestors, mode_post, mode_post_spare)
    if lane == 0 and stats[b, ST_REMAIN] > wp.float64(0.0):
        more[stage + 1] = 1


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


@wp.func
def integrity_lanes(b: int, lane: int, n_per: int, offset: int, seeds: wp.array(dtype=wp.int32), params: UpdateParams,
                    stats: wp.array2d(dtype=wp.float64), integrity: wp.array2d(dtype=wp.float64),
                    kernel_chol: wp.array(dtype=wp.mat33), dp: wp.array(dtype=wp.vec3),
                    logw: wp.array(dtype=wp.float32)):
    """Filter b's integrity monitor over the lanes of its block: :func:`integrity_step` (lane 0), a barrier,
    :func:`respread_particle` (every lane must call it)."""
    if lane == 0:
        integrity_step(b, params, stats, integrity, kernel_chol)
    block_sync()
    if stats[b, ST_RESPREAD] == wp.float64(0.0):  # (read once: the loop's own test re-read it per particle)
        return
    for k in range(lane, n_per, wp.block_dim()):
        respread_particle(b * n_per + k, n_per, offset, seeds, params, stats, dp, logw)


@wp.kernel
def record_block_kernel(
    n_per: int,
    params: UpdateParams,
    measurement_update: int,
    closed_loop: int,
    offset: int,
    advance: int,
    seeds: wp.array(dtype=wp.int32),
    kernel_chol: wp.array(dtype=wp.mat33),
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
    with_modes: int,
    m: int,
    table: wp.array(dtype=modes_vec),
    mode_post: wp.array(dtype=modes_vec),
    mode_var: wp.array(dtype=modes_vec),
    mode_mean: wp.array(dtype=modes_vec),
    more: wp.array(dtype=wp.int32),
):
    """The record and feedback of filter b in one CUDA block (:data:`RECORD_BLOCK_DIM` lanes, so the block sum is
    :data:`summary_kernel`'s): first the integrity monitor (:func:`integrity_lanes`: :data:`integrity_kernel` and
    :data:`respread_kernel`), with ``with_modes`` then the map-error modes' prior for the next scan
    (:data:`modes_finalize_kernel` over the lanes, a barrier, :data:`modes_variance_kernel` on lane 0: the modes need
    the re-spread's decision, the record none of theirs), then :func:`summary_partial` (lane per chunk),
    :func:`record_summary`, :func:`update_covariance_lanes` and in closed loop :func:`reset_particle`, barriers
    between (:data:`summary_partials_kernel`, :data:`summary_kernel`, :data:`covariance_update_kernel`,
    :data:`reset_kernel`: the same bits). With ``advance`` (one filter: no other block reads the slot) lane 0 then
    ends the update (:func:`end_update`: the slot advances, the stage flags clear), else a launch of its own does
    (:data:`advance_slot_kernel`, after every filter's record)."""
    b, lane = wp.tid()
    bd = wp.block_dim()
    integrity_lanes(b, lane, n_per, offset, seeds, params, stats, integrity, kernel_chol, dp, logw)
    block_sync()
    if with_modes != 0:  # (the same for every lane of the block: its barrier is reached by all)
        for k in range(lane, n_per, bd):
            modes_finalize(b * n_per + k, n_per, m, table, stats, mode_post, mode_var, mode_mean)
        block_sync()
        if lane == 0:
            modes_variance(b, m, table, stats, mode_var)
    for c in range(lane, N_CHUNKS, bd):
        summary_partial(b, c, n_per, logw, dp, lin, summary_sums)
    block_sync()
    record_summary(b, lane, params, summary_sums, stats, integrity, slot, history, feedback)
    block_sync()
    update_covariance_lanes(b, lane, measurement_update, closed_loop, feedback, slot, cov, pos, vel, quat, accel_bias,
                            gyro_bias, injections, nominal_hist, p_hist)
    block_sync()
    if closed_loop != 0:
        for k in range(lane, n_per, bd):
            reset_particle(b * n_per + k, n_per, feedback, dp, lin)
    if advance != 0 and lane == 0:  # (no lane reads the slot after the barrier above)
        end_update(slot, more)
