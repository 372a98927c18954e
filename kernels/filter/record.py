"""The update's record and feedback: summary sums, history, P's measurement update and the closed-loop injection
(the moments an estimate reads: :mod:`warptan.kernels.filter.readout`)."""

import warp as wp

from warptan.kernels.block import block_sync
from warptan.kernels.filter.common import (
    FB_APPLIED,
    FB_CONVERGED,
    FB_LAM,
    FB_MEAN_DP,
    FB_MEAN_L,
    H_APPLIED,
    H_BAD,
    H_COV_DP,
    H_ESS,
    H_MEAN_DP,
    H_MEAN_L,
    H_NIS,
    H_NIS_AVG,
    H_NIS_POST,
    H_RESAMPLES,
    H_RESPREAD,
    H_SKIPPED,
    H_STAGES,
    H_SUM_W,
    H_UNPREDICTABLE,
    H_VAR_L,
    IN_MEAN,
    IN_SINCE,
    NOM_BA,
    NOM_BG,
    NOM_POS,
    NOM_QUAT,
    NOM_VEL,
    ST_APPLIED,
    ST_BAD,
    ST_ESS,
    ST_LAM,
    ST_NIS,
    ST_NIS_MIN,
    ST_RESAMPLES,
    ST_RESPREAD,
    ST_SKIP,
    ST_STAGES,
    ST_UNPREDICTABLE,
    WARP_LANES,
    UpdateParams,
    chunk_range,
    chunk_sum,
    pair_products,
    stats_row,
    summary_vec,
    sym_from,
    vec12,
    weighted_cov,
)
from warptan.kernels.frames import quat_exp_wxyz, quat_log_wxyz, quat_mul_wxyz
from warptan.kernels.nav import block_of, quat_mul_exp_d, skew_d

wp.set_module_options({"enable_backward": False})

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
    # what lane 0 reads, read before it writes anything (a load after a store waits for it)
    st = stats_row(stats, b)
    converged = feedback[b, FB_CONVERGED]
    since = integrity[b, IN_SINCE]
    nis_avg = integrity[b, IN_MEAN]
    t = slot[0]
    tot = summary_vec()
    if lane < WARP_LANES:  # (the block's first warp; the CPU's one thread)
        for a in range(34):
            tot[a] = chunk_sum(b, lane, a, partial_in)
    if lane != 0:
        return
    s = tot[0]
    inv = wp.float64(1.0) / s  # (one division: a float64 division is a chain of its own on CUDA)
    applied = st[ST_APPLIED]
    if st[ST_SKIP] != wp.float64(0.0):
        applied = wp.float64(0.0)
    feedback[b, FB_APPLIED] = applied
    gate = wp.float64(1.0)  # the verdict the particles' Kalman update read (the previous update's), not yet renewed
    if params.gate_linear != 0:
        gate = converged
    for a in range(6):
        feedback[b, FB_LAM + a] = gate * applied * st[ST_LAM + a]
    for a in range(3):
        feedback[b, FB_MEAN_DP + a] = tot[1 + a] * inv
    for a in range(12):
        feedback[b, FB_MEAN_L + a] = tot[10 + a] * inv
    judged = since >= wp.float64(params.integrity_min_updates)
    ok = nis_avg <= wp.float64(params.integrity_threshold) and st[ST_RESPREAD] == wp.float64(0.0)
    feedback[b, FB_CONVERGED] = wp.where(judged and ok, wp.float64(1.0), wp.float64(0.0))
    if t >= history.shape[0]:
        return
    cov = weighted_cov(inv, wp.vec3d(tot[1], tot[2], tot[3]), wp.vec3d(tot[4], tot[5], tot[6]),
                       wp.vec3d(tot[7], tot[8], tot[9]))
    history[t, b, H_ESS] = st[ST_ESS]
    history[t, b, H_RESAMPLES] = st[ST_RESAMPLES]
    history[t, b, H_RESPREAD] = st[ST_RESPREAD]
    history[t, b, H_BAD] = st[ST_BAD]
    history[t, b, H_UNPREDICTABLE] = st[ST_UNPREDICTABLE]
    history[t, b, H_SUM_W] = s
    for a in range(3):
        history[t, b, H_MEAN_DP + a] = tot[1 + a] * inv
        history[t, b, H_COV_DP + a] = cov[a, a]
    history[t, b, H_COV_DP + 3] = cov[0, 1]
    history[t, b, H_COV_DP + 4] = cov[0, 2]
    history[t, b, H_COV_DP + 5] = cov[1, 2]
    history[t, b, H_STAGES] = st[ST_STAGES]
    history[t, b, H_NIS] = st[ST_NIS_MIN]
    history[t, b, H_NIS_POST] = st[ST_NIS]
    history[t, b, H_NIS_AVG] = nis_avg
    history[t, b, H_SKIPPED] = st[ST_SKIP]
    history[t, b, H_APPLIED] = st[ST_APPLIED]
    for a in range(12):
        mean = tot[10 + a] * inv
        history[t, b, H_MEAN_L + a] = mean
        history[t, b, H_VAR_L + a] = wp.max(tot[22 + a] * inv - mean * mean, wp.float64(0.0))


@wp.kernel
def summary_kernel(params: UpdateParams, partial_in: wp.array3d(dtype=wp.float64), stats: wp.array2d(dtype=wp.float64),
                   integrity: wp.array2d(dtype=wp.float64), slot: wp.array(dtype=wp.int32),
                   history: wp.array3d(dtype=wp.float64), feedback: wp.array2d(dtype=wp.float64)):
    """One thread per (b, lane): :func:`record_summary`."""
    b, lane = wp.tid()
    record_summary(b, lane, params, partial_in, stats, integrity, slot, history, feedback)



@wp.func
def record_nominal(
    b: int,
    t: int,
    pos: wp.array(dtype=wp.vec3d),
    vel: wp.array(dtype=wp.vec3d),
    quat: wp.array(dtype=wp.vec4d),
    accel_bias: wp.array(dtype=wp.vec3d),
    gyro_bias: wp.array(dtype=wp.vec3d),
    nominal_hist: wp.array3d(dtype=wp.float64),
):
    """The nominal INS at this update into ``nominal_hist[t, b]`` (p, v, q, b_a, b_g: before any injection)."""
    for a in range(3):
        nominal_hist[t, b, NOM_POS + a] = pos[b][a]
        nominal_hist[t, b, NOM_VEL + a] = vel[b][a]
        nominal_hist[t, b, NOM_BA + a] = accel_bias[b][a]
        nominal_hist[t, b, NOM_BG + a] = gyro_bias[b][a]
    for a in range(4):
        nominal_hist[t, b, NOM_QUAT + a] = quat[b][a]


@wp.func
def attitude_gain(b: int, feedback: wp.array2d(dtype=wp.float64), p_tt: wp.mat33d) -> wp.mat33d:
    """``Λ̄ (I + P_θθ Λ̄)⁻¹`` of P's measurement update (Λ̄ = ``feedback`` FB_LAM)."""
    lam = sym_from(feedback, b, FB_LAM)
    return lam * wp.inverse(wp.identity(n=3, dtype=wp.float64) + p_tt * lam)


@wp.func
def measured_block(p_rc: wp.mat33d, c_r: wp.mat33d, c_c: wp.mat33d, gain: wp.mat33d) -> wp.mat33d:
    """Block (r, c) of ``P - P_:θ gain P_θ:`` from the blocks ``P_rθ``, ``P_cθ`` read before any was overwritten."""
    return p_rc - (c_r * gain) * wp.transpose(c_c)


@wp.func
def symmetrise_pair(b: int, r: int, c: int, cov: wp.array3d(dtype=wp.mat33d)):
    """Blocks (r, c) and (c, r), r ≤ c, set to their symmetric mean."""
    m = wp.float64(0.5) * (cov[b, r, c] + wp.transpose(cov[b, c, r]))
    cov[b, r, c] = m
    cov[b, c, r] = wp.transpose(m)


@wp.func
def inject_closed_loop(
    b: int,
    feedback: wp.array2d(dtype=wp.float64),
    cov: wp.array3d(dtype=wp.mat33d),
    pos: wp.array(dtype=wp.vec3d),
    vel: wp.array(dtype=wp.vec3d),
    quat: wp.array(dtype=wp.vec4d),
    accel_bias: wp.array(dtype=wp.vec3d),
    gyro_bias: wp.array(dtype=wp.vec3d),
    injections: wp.array(dtype=wp.int32),
):
    """Closed loop: nominal ⊕ the mean error, ``P <- G P Gᵀ``, ``injections[b] += 1`` (see
    :func:`update_covariance`)."""
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
    """One thread per filter, after the update's record (float64, on the filter's device;
    :func:`update_covariance_lanes` is the same work over a block's lanes, the same bits):

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
        record_nominal(b, t, pos, vel, quat, accel_bias, gyro_bias, nominal_hist)
    if measurement_update != 0:
        gain = attitude_gain(b, feedback, cov[b, 1, 1])
        c0 = cov[b, 0, 1]
        c1 = cov[b, 1, 1]
        c2 = cov[b, 2, 1]
        c3 = cov[b, 3, 1]
        for r in range(4):
            for c in range(4):  # P_:θ's blocks, read before any is overwritten
                cov[b, r, c] = measured_block(cov[b, r, c], block_of(r, c0, c1, c2, c3, c3), block_of(c, c0, c1, c2,
                                              c3, c3), gain)
        for r in range(4):
            for c in range(r, 4):
                symmetrise_pair(b, r, c, cov)
    if record:
        for r in range(4):
            blk = cov[b, r, r]
            for a in range(3):
                p_hist[t, b, 3 * r + a] = blk[a, a]
    if closed_loop == 0 or feedback[b, FB_CONVERGED] == wp.float64(0.0):
        return
    inject_closed_loop(b, feedback, cov, pos, vel, quat, accel_bias, gyro_bias, injections)


@wp.func
def update_covariance_lanes(
    b: int,
    lane: int,
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
    """:func:`update_covariance` over the lanes of filter b's block (at least 16; barriers between the phases):
    lane 4 r + c forms P's block (r, c), then the pairs r ≤ c are symmetrised, then the record; lane 0 records the
    nominal and injects (a block of fewer than 16 lanes runs :func:`update_covariance` on lane 0). Each block sees
    the operations of the one-thread form, in which a block was a chain of dependent global reads and writes."""
    if wp.block_dim() < 16:  # (the CPU's tiled launches run a block as one thread)
        if lane == 0:
            update_covariance(b, measurement_update, closed_loop, feedback, slot, cov, pos, vel, quat, accel_bias,
                              gyro_bias, injections, nominal_hist, p_hist)
        return
    t = slot[0]
    record = t < nominal_hist.shape[0]
    if lane == 0 and record:
        record_nominal(b, t, pos, vel, quat, accel_bias, gyro_bias, nominal_hist)
    r = lane // 4
    c = lane % 4
    if measurement_update != 0:
        m = wp.mat33d()
        if lane < 16:
            m = measured_block(cov[b, r, c], cov[b, r, 1], cov[b, c, 1], attitude_gain(b, feedback, cov[b, 1, 1]))
        block_sync()  # every lane has read P
        if lane < 16:
            cov[b, r, c] = m
        block_sync()
        if lane < 16 and r <= c:
            symmetrise_pair(b, r, c, cov)
        block_sync()
    if record and lane < 4:
        blk = cov[b, lane, lane]
        for a in range(3):
            p_hist[t, b, 3 * lane + a] = blk[a, a]
    block_sync()  # the record has read P
    if lane == 0 and closed_loop != 0 and feedback[b, FB_CONVERGED] != wp.float64(0.0):
        inject_closed_loop(b, feedback, cov, pos, vel, quat, accel_bias, gyro_bias, injections)


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
    ``dθ_i <- Log(Exp(θ̂)⁻¹ Exp(dθ_i))`` (right perturbations, design notes §3). Filters not injected (FB_CONVERGED = 0)
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



@wp.func
def end_update(slot: wp.array(dtype=wp.int32), more: wp.array(dtype=wp.int32)):
    """The update's end: the history slot advances; the tempering stages' flags (``more[s]``: stage s runs) clear for
    the next update."""
    slot[0] = slot[0] + 1
    for s in range(more.shape[0]):
        more[s] = 0


@wp.kernel
def advance_slot_kernel(slot: wp.array(dtype=wp.int32), more: wp.array(dtype=wp.int32)):
    """One thread, after every filter's record: :func:`end_update`."""
    end_update(slot, more)
