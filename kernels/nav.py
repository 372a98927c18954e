"""The nominal INS and the shared Kalman covariance of B filters, one measurement interval per launch (SPEC §3, §6).

Runs on the host (the CPU device, float64): one thread per filter b steps through the K IMU samples of the
interval. Per sample, from the nominal state *before* the step (its own step ``dt_k``, ``imu[b, k, 2][0]``: a
recorded flight's samples need not be evenly spaced; the noise per step scales as ``dt_k / dt``):

* the error transition blocks (3×3 blocks, order ``[dp, dv, dth, dba, dbg]``; see :mod:`warptan.ins`)::

      A^n = [dt I, dt/2 A, dt/2 B, 0]            A = -R [a]x dt,  B = -R dt
      A^l = [[I, A, B, 0], [0, E, 0, J], [0, 0, I, 0], [0, 0, 0, I]]   E = Exp(w dt)ᵀ, J = -J_r(w dt) dt

* the Riccati recursion of the marginalized filter (SPEC §6 step 5)::

      N_k = A^n P A^nᵀ + Q^n,  L_k = A^l P A^nᵀ N_k⁻¹,  P <- A^l P A^lᵀ + Q^l - L_k N_k L_kᵀ

* the mechanization of :func:`warptan.ins.mechanize`.

It also composes what the interval does to a particle ``x = [dp, l]`` (15): each step is
``x <- T_k x + G_k e_k`` with ``T_k = [[I, A^n], [0, A^l]]``, ``G_k = [I; L_k]``, ``e_k ~ N(0, N_k)``, so over
the interval ``x <- Φ x + w`` with ``Φ = T_K ... T_1`` and ``w ~ N(0, S)``,
``S = Σ_k (T_K ... T_k+1) G_k N_k G_kᵀ (...)ᵀ``. The particle kernel then needs one 15×15 product and one
15-vector of normal numbers per particle and interval, whatever K is: the same distribution as stepping
each particle K times, at a fraction of the cost. Matrices are kept as 3×3 blocks (``mat33d``) so that
the sparse structure of ``T_k`` is used.
"""

import warp as wp

wp.set_module_options({"enable_backward": False, "max_unroll": 4})

GRAVITY_D = wp.constant(9.80665)
INT_STEPS = wp.constant(0)
"""Columns of an interval's integers (B, N_INTS): the IMU samples buffered, the particle-move seed, the resampling
seed."""
INT_MOVE_SEED = wp.constant(1)
INT_RESAMPLE_SEED = wp.constant(2)
N_INTS = 3


@wp.func
def rot_d(q: wp.vec4d) -> wp.mat33d:
    """``R(q)`` of a unit quaternion [w, x, y, z] (float64)."""
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    one = wp.float64(1.0)
    two = wp.float64(2.0)
    return wp.mat33d(
        one - two * (y * y + z * z), two * (x * y - w * z), two * (x * z + w * y),
        two * (x * y + w * z), one - two * (x * x + z * z), two * (y * z - w * x),
        two * (x * z - w * y), two * (y * z + w * x), one - two * (x * x + y * y),
    )


@wp.func
def skew_d(v: wp.vec3d) -> wp.mat33d:
    z = wp.float64(0.0)
    return wp.mat33d(z, -v[2], v[1], v[2], z, -v[0], -v[1], v[0], z)


@wp.func
def sym_d(m: wp.mat33d) -> wp.mat33d:
    return wp.float64(0.5) * (m + wp.transpose(m))


@wp.func
def apply_t(x0: wp.mat33d, x1: wp.mat33d, x2: wp.mat33d, x3: wp.mat33d, x4: wp.mat33d, dt: wp.float64,
            a: wp.mat33d, b: wp.mat33d, e: wp.mat33d, j: wp.mat33d):
    """``T_k`` times one block column ``[x0..x4]`` of a 15×15 matrix."""
    ax2 = a * x2
    bx3 = b * x3
    y0 = x0 + dt * x1 + wp.float64(0.5) * dt * (ax2 + bx3)
    y1 = x1 + ax2 + bx3
    y2 = e * x2 + j * x4
    return y0, y1, y2


@wp.func
def apply_l(x1: wp.mat33d, x2: wp.mat33d, x3: wp.mat33d, x4: wp.mat33d, a: wp.mat33d, b: wp.mat33d,
            e: wp.mat33d, j: wp.mat33d):
    """``A^l`` times one block column ``[x1..x4]`` of a 12×k matrix (rows 3 and 4 are unchanged)."""
    return x1 + a * x2 + b * x3, e * x2 + j * x4


@wp.func
def quat_mul_exp_d(q: wp.vec4d, th: wp.vec3d) -> wp.vec4d:
    """``q ⊗ Exp(θ)`` normalised (float64, [w, x, y, z]; series below 1e-8 rad)."""
    half = wp.float64(0.5)
    angle = wp.length(th)
    ha = half * angle
    ew = wp.cos(ha)
    sc = half
    if angle < wp.float64(1.0e-8):
        ew = wp.float64(1.0) - angle * angle / wp.float64(8.0)
        sc = half - angle * angle / wp.float64(48.0)
    else:
        sc = wp.sin(ha) / angle
    ex = sc * th
    nq = wp.vec4d(
        q[0] * ew - q[1] * ex[0] - q[2] * ex[1] - q[3] * ex[2],
        q[0] * ex[0] + q[1] * ew + q[2] * ex[2] - q[3] * ex[1],
        q[0] * ex[1] - q[1] * ex[2] + q[2] * ew + q[3] * ex[0],
        q[0] * ex[2] + q[1] * ex[1] - q[2] * ex[0] + q[3] * ew,
    )
    return nq / wp.length(nq)


@wp.func
def block_of(k: int, m0: wp.mat33d, m1: wp.mat33d, m2: wp.mat33d, m3: wp.mat33d, m4: wp.mat33d) -> wp.mat33d:
    """The k-th of five blocks (a block column held in locals)."""
    if k == 1:
        return m1
    if k == 2:
        return m2
    if k == 3:
        return m3
    if k == 4:
        return m4
    return m0


NAV_BLOCK_DIM = 32
"""Threads of a CUDA block that runs one filter's interval (:data:`nav_interval_kernels`): one works, the others
return at once, so each filter has a multiprocessor and its L1 cache to itself. As 100 threads of one launch, the
filters' ~7 KB working sets shared the caches of a few multiprocessors: 100 filters took 1.9 ms on an H100 where
one took 0.27 ms."""


def _nav_interval(tiled: bool):
    @wp.kernel
    def nav_interval_kernel(
        row0: int,
        counts: wp.array2d(dtype=wp.int32),
        nominal_dt: wp.float64,
        q_pos: wp.array(dtype=wp.float64),
        q_rough: wp.float64,
        q_lin: wp.vec4d,
        q_vel_down: wp.array(dtype=wp.float64),
        imu: wp.array3d(dtype=wp.vec3d),
        pos: wp.array(dtype=wp.vec3d),
        vel: wp.array(dtype=wp.vec3d),
        quat: wp.array(dtype=wp.vec4d),
        accel_bias: wp.array(dtype=wp.vec3d),
        gyro_bias: wp.array(dtype=wp.vec3d),
        cov: wp.array3d(dtype=wp.mat33d),
        phi: wp.array3d(dtype=wp.mat33d),
        noise: wp.array3d(dtype=wp.mat33d),
        chol_scratch: wp.array3d(dtype=wp.float64),
        phi_out: wp.array3d(dtype=wp.mat33),
        chol_out: wp.array3d(dtype=wp.mat33),
        pose_out: wp.array2d(dtype=wp.float64),
        att_cov_out: wp.array(dtype=wp.mat33),
        p_col_out: wp.array2d(dtype=wp.mat33),
    ):
        """Thread b: K = ``counts[b, INT_STEPS]`` IMU samples (specific force ``imu[b, k, 0]``, body rate
        ``imu[b, k, 1]``, step length ``imu[b, k, 2][0]`` in s; ``nominal_dt`` is the step the noise terms are given
        for) of filter ``b = row0 + t``: advances its nominal state and ``cov`` (P, 4×4 blocks) in place;
        writes Φ and the lower Cholesky factor of S (5×5 blocks, float32), the nominal pose ``[p (3), q (4)]`` at the
        end of the interval, and what the update's kernels read of P: ``P_θθ`` (``att_cov_out``) and the column blocks
        ``P_:θ`` (``p_col_out``).
        ``q_lin`` = diagonal of Q^l per block (dv, dth, dba, dbg); ``q_pos[b]`` = diagonal of Q^n (the position noise
        the Kalman part models, in N_k and L_k); ``q_rough`` = per-step variance of the roughening, added to the
        particles' dp only (``S_dpdp += K q_rough I``: T_k leaves a dp-only noise on dp), so that L_k never reads it
        as velocity. ``q_vel_down[b]`` is added to the down velocity's Q^l (a map-error offset's change along the track,
        :meth:`warptan.measurement.Likelihood.offset_process`; 0 without one)."""
        if wp.static(tiled):
            t, lane = wp.tid()
            if lane != 0:
                return
        else:
            t = wp.tid()
        b = row0 + t
        zero = wp.mat33d()
        eye = wp.identity(n=3, dtype=wp.float64)
        half = wp.float64(0.5)
        for r in range(5):
            for c in range(5):
                phi[b, r, c] = zero
                noise[b, r, c] = zero
            phi[b, r, r] = eye
        p = pos[b]
        v = vel[b]
        q = quat[b]
        ba = accel_bias[b]
        bg = gyro_bias[b]
        n_steps = counts[b, INT_STEPS]
        steps = wp.float64(0.0)  # Σ dt_k / dt: the interval in nominal steps (n_steps when evenly spaced)
        for k in range(n_steps):
            f = imu[b, k, 0]
            w = imu[b, k, 1]
            dt = imu[b, k, 2][0]
            scale = dt / nominal_dt  # exactly 1 for a nominal step: the same bits as a fixed step
            steps = steps + scale
            rot = rot_d(q)
            acc = f - ba
            wdt = (w - bg) * dt
            a = -(rot * skew_d(acc)) * dt
            bm = -rot * dt
            angle = wp.length(wdt)
            kx = skew_d(wdt)
            kk = kx * kx
            c1 = wp.float64(1.0)
            c2 = half
            j1 = half
            j2 = wp.float64(1.0) / wp.float64(6.0)
            if angle >= wp.float64(1.0e-8):
                c1 = wp.sin(angle) / angle
                c2 = (wp.float64(1.0) - wp.cos(angle)) / (angle * angle)
                j1 = c2
                j2 = (angle - wp.sin(angle)) / (angle * angle * angle)
            e = wp.transpose(eye + c1 * kx + c2 * kk)
            jm = -(eye - j1 * kx + j2 * kk) * dt
            # ---- Riccati (P in 4×4 blocks: dv, dth, dba, dbg)
            pa0 = dt * cov[b, 0, 0] + half * dt * (cov[b, 0, 1] * wp.transpose(a) + cov[b, 0, 2] * wp.transpose(bm))
            pa1 = dt * cov[b, 1, 0] + half * dt * (cov[b, 1, 1] * wp.transpose(a) + cov[b, 1, 2] * wp.transpose(bm))
            pa2 = dt * cov[b, 2, 0] + half * dt * (cov[b, 2, 1] * wp.transpose(a) + cov[b, 2, 2] * wp.transpose(bm))
            pa3 = dt * cov[b, 3, 0] + half * dt * (cov[b, 3, 1] * wp.transpose(a) + cov[b, 3, 2] * wp.transpose(bm))
            nk = sym_d(dt * pa0 + half * dt * (a * pa1 + bm * pa2) + (q_pos[b] * scale) * eye)
            l0, l1 = apply_l(pa0, pa1, pa2, pa3, a, bm, e, jm)
            inv_nk = wp.inverse(nk)
            g0 = l0 * inv_nk
            g1 = l1 * inv_nk
            g2 = pa2 * inv_nk
            g3 = pa3 * inv_nk
            # P <- A^l P A^lᵀ: A^l on the block columns, then on the rows (transposed)
            for c in range(4):
                y0, y1 = apply_l(cov[b, 0, c], cov[b, 1, c], cov[b, 2, c], cov[b, 3, c], a, bm, e, jm)
                cov[b, 0, c] = y0
                cov[b, 1, c] = y1
            for r in range(4):
                y0, y1 = apply_l(wp.transpose(cov[b, r, 0]), wp.transpose(cov[b, r, 1]), wp.transpose(cov[b, r, 2]),
                                 wp.transpose(cov[b, r, 3]), a, bm, e, jm)
                cov[b, r, 0] = wp.transpose(y0)
                cov[b, r, 1] = wp.transpose(y1)
            # - L N Lᵀ + Q^l, symmetrised
            for r in range(4):
                gn = block_of(r + 1, eye, g0, g1, g2, g3) * nk
                for c in range(4):
                    cov[b, r, c] = cov[b, r, c] - gn * wp.transpose(block_of(c + 1, eye, g0, g1, g2, g3))
                cov[b, r, r] = cov[b, r, r] + (q_lin[r] * scale) * eye
            if q_vel_down[b] > wp.float64(0.0):
                dv = cov[b, 0, 0]
                dv[2, 2] = dv[2, 2] + q_vel_down[b] * scale
                cov[b, 0, 0] = dv
            for r in range(4):
                cov[b, r, r] = sym_d(cov[b, r, r])
                for c in range(r + 1, 4):
                    m = half * (cov[b, r, c] + wp.transpose(cov[b, c, r]))
                    cov[b, r, c] = m
                    cov[b, c, r] = wp.transpose(m)
            # ---- interval composition: Φ <- T Φ, S <- T S Tᵀ + G N Gᵀ, G = [I; L]
            for c in range(5):
                y0, y1, y2 = apply_t(phi[b, 0, c], phi[b, 1, c], phi[b, 2, c], phi[b, 3, c], phi[b, 4, c], dt, a, bm, e,
                                     jm)
                phi[b, 0, c] = y0
                phi[b, 1, c] = y1
                phi[b, 2, c] = y2
                y0, y1, y2 = apply_t(noise[b, 0, c], noise[b, 1, c], noise[b, 2, c], noise[b, 3, c], noise[b, 4, c], dt,
                                     a, bm, e, jm)
                noise[b, 0, c] = y0
                noise[b, 1, c] = y1
                noise[b, 2, c] = y2
            for r in range(5):
                y0, y1, y2 = apply_t(wp.transpose(noise[b, r, 0]), wp.transpose(noise[b, r, 1]),
                                     wp.transpose(noise[b, r, 2]), wp.transpose(noise[b, r, 3]),
                                     wp.transpose(noise[b, r, 4]), dt, a, bm, e, jm)
                noise[b, r, 0] = wp.transpose(y0)
                noise[b, r, 1] = wp.transpose(y1)
                noise[b, r, 2] = wp.transpose(y2)
            for r in range(5):
                gn = block_of(r, eye, g0, g1, g2, g3) * nk
                for c in range(5):
                    noise[b, r, c] = noise[b, r, c] + gn * wp.transpose(block_of(c, eye, g0, g1, g2, g3))
            # ---- mechanization (warptan.ins._step_inplace)
            an = rot * acc + wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(GRAVITY_D))
            p = p + v * dt + half * dt * dt * an
            v = v + an * dt
            q = quat_mul_exp_d(q, wdt)
        pos[b] = p
        vel[b] = v
        quat[b] = q
        noise[b, 0, 0] = noise[b, 0, 0] + steps * q_rough * eye
        # ---- outputs: Φ (float32) and chol(S), scalar Cholesky on a 15×15 scratch (semi-definite safe)
        for r in range(5):
            for c in range(5):
                phi_out[b, r, c] = wp.mat33(phi[b, r, c])
                blk = half * (noise[b, r, c] + wp.transpose(noise[b, c, r]))
                for i in range(3):
                    for j in range(3):
                        chol_scratch[b, 3 * r + i, 3 * c + j] = blk[i, j]
        for jj in range(15):
            dd = chol_scratch[b, jj, jj]
            for m1 in range(jj):
                dd -= chol_scratch[b, jj, m1] * chol_scratch[b, jj, m1]
            if dd > wp.float64(1.0e-30):
                dd = wp.sqrt(dd)
            else:
                dd = wp.float64(0.0)
            chol_scratch[b, jj, jj] = dd
            for ii in range(jj + 1, 15):
                s = chol_scratch[b, ii, jj]
                for m2 in range(jj):
                    s -= chol_scratch[b, ii, m2] * chol_scratch[b, jj, m2]
                if dd > wp.float64(0.0):
                    chol_scratch[b, ii, jj] = s / dd
                else:
                    chol_scratch[b, ii, jj] = wp.float64(0.0)
            for i2 in range(jj):
                chol_scratch[b, i2, jj] = wp.float64(0.0)
        for r in range(5):
            for c in range(5):
                lo = wp.mat33d()
                for i in range(3):
                    for j in range(3):
                        lo[i, j] = chol_scratch[b, 3 * r + i, 3 * c + j]
                chol_out[b, r, c] = wp.mat33(lo)
        for i in range(3):
            pose_out[b, i] = p[i]
        for i in range(4):
            pose_out[b, 3 + i] = q[i]
        att_cov_out[b] = wp.mat33(cov[b, 1, 1])
        for r in range(4):
            p_col_out[b, r] = wp.mat33(cov[b, r, 1])

    return nav_interval_kernel


nav_interval_kernels = {tiled: _nav_interval(tiled) for tiled in (True, False)}
"""The interval kernel: ``[True]`` one CUDA block of :data:`NAV_BLOCK_DIM` threads per filter
(``wp.launch_tiled``), ``[False]`` one thread per filter (the CPU, whose launches are split across cores)."""
nav_interval_kernel = nav_interval_kernels[False]
