# About 500 lines on purpose: the nominal INS, the Riccati recursion and the interval's composition of one kernel,
# in its CPU (a thread per filter) and CUDA (a block per filter) forms, which share every function.
"""The nominal INS and the shared Kalman covariance of B filters, one measurement interval per launch (design
notes §3, §6).

Float64, on the filter's device: on the CPU one thread per filter b steps through the K IMU samples of the interval;
on CUDA one block per filter whose lanes share the work of each sample (:data:`NAV_BLOCK_DIM`). Per sample, from the
nominal state *before* the step (its own step ``dt_k``, ``imu[b, k, 2][0]``: a recorded flight's samples need not be
evenly spaced; the noise per step scales as ``dt_k / dt``):

* the error transition blocks (3×3 blocks, order ``[dp, dv, dth, dba, dbg]``; see :mod:`warptan.nav.ins`)::

      A^n = [dt I, dt/2 A, dt/2 B, 0]            A = -R [a]x dt,  B = -R dt
      A^l = [[I, A, B, 0], [0, E, 0, J], [0, 0, I, 0], [0, 0, 0, I]]   E = Exp(w dt)ᵀ, J = -J_r(w dt) dt

* the Riccati recursion of the marginalized filter (design notes §6 step 5)::

      N_k = A^n P A^nᵀ + Q^n,  L_k = A^l P A^nᵀ N_k⁻¹,  P <- A^l P A^lᵀ + Q^l - L_k N_k L_kᵀ

* the mechanization of :func:`warptan.nav.ins.mechanize`.

It also composes what the interval does to a particle ``x = [dp, l]`` (15): each step is
``x <- T_k x + G_k e_k`` with ``T_k = [[I, A^n], [0, A^l]]``, ``G_k = [I; L_k]``, ``e_k ~ N(0, N_k)``, so over
the interval ``x <- Φ x + w`` with ``Φ = T_K ... T_1`` and ``w ~ N(0, S)``,
``S = Σ_k (T_K ... T_k+1) G_k N_k G_kᵀ (...)ᵀ``. The particle kernel then needs one 15×15 product and one
15-vector of normal numbers per particle and interval, whatever K is: the same distribution as stepping
each particle K times, at a fraction of the cost. Matrices are kept as 3×3 blocks (``mat33d``) so that
the sparse structure of ``T_k`` is used.
"""

import warp as wp

from warptan.kernels.block import block_sync, span

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


NAV_BLOCK_DIM = 128
"""Threads of a CUDA block that runs one filter's interval (:data:`nav_interval_kernels`; four warps): the lanes
share the 3×3 blocks of the interval's matrices (:func:`span`) and meet at :func:`block_sync` between the phases of
a step. Each warp has its own pieces, side by side: P's on the first, Φ's and S's on the second (:data:`SIDE_LANE`),
the gains' on the third (:data:`GAIN_LANE`: ``P A^nᵀ`` while the first warp applies ``A^l`` to P's columns, ``N_k``
and the gains while it applies it to the rows), and the nominal INS on the fourth (:data:`NOMINAL_LANE`: the
mechanization of step k and the transition blocks of step k + 1 while the others run step k). With two warps every
lane formed the step's transition blocks, ``N_k``, its inverse and the gains itself, and advanced the nominal state:
~1 200 of the ~2 300 instructions a warp issued per sample, on the path of every step (ncu, H100: 255 registers, a
warp issuing every 4.3 cycles). A 10-sample interval went 56.5 → 42.0 µs, 100 filters 60.6 → 49.5 µs
(``scripts/bench_nav_interval.py``). Tried and slower: the nominal lane's work spread over three phases (43.3 µs), the
transition blocks read again after each barrier instead of held (47.8 µs). One thread per filter took 0.27 ms for a
10-sample interval (a chain of ~270 dependent 3×3 products a sample, each waiting on its loads); as 100 threads of one
launch the filters' ~7 KB working sets shared the caches of a few multiprocessors (1.9 ms for 100 filters): a block per
filter keeps a multiprocessor each."""


SIDE_LANE = wp.constant(32)
"""The first lane of the second warp: where the pieces of Φ and S start (those of P start at lane 0)."""
GAIN_LANE = wp.constant(64)
"""The first lane of the third warp: ``P A^nᵀ`` by block rows, then ``N_k`` and the gains (four pieces each)."""
NOMINAL_LANE = wp.constant(96)
"""The lane of the fourth warp that advances the nominal state and forms the next step's transition blocks."""

COV_AT = wp.constant(0)
"""Where the tiled kernel keeps each matrix in the block's shared memory (float64 slots): P (4×4 blocks), Φ and S
(5×5 blocks), the 15×15 Cholesky scratch."""
PHI_AT = wp.constant(144)
NOISE_AT = wp.constant(369)
CHOL_AT = wp.constant(594)
NAV_SHARED_SLOTS = 819
W_Q = wp.constant(0)
W_PA = wp.constant(8)
W_GAIN = wp.constant(12)
W_NK = wp.constant(16)
W_TERMS = wp.constant(17)
"""The blocks of the steps' scratch (:func:`w_get`): they share the Cholesky's slots, which only the interval's end
uses: the rows 0–1 of ``A^l P`` (``W_Q``, 2×4 blocks), ``P A^nᵀ`` by block rows (``W_PA``), the gains ``L_k N_k⁻¹``
and ``P A^nᵀ N_k⁻¹`` (``W_GAIN``), ``N_k`` (``W_NK``) and a step's transition blocks ``A, B, E, J`` (``W_TERMS``, two
steps alternating: 25 blocks, the 225 slots of the 15×15 scratch). On the CPU they are the filter's ``chol_scratch``
row."""


@wp.func_native("""
#if defined(__CUDA_ARCH__)
__shared__ double nav_slots[819];
if (store) nav_slots[i] = v;
return nav_slots[i];
#else
return v;
#endif
""")
def shared_slot(i: int, v: wp.float64, store: int) -> wp.float64:
    """Slot ``i`` of the block's shared float64 buffer (:data:`NAV_SHARED_SLOTS`), written first when ``store``
    (CUDA; one buffer per block). The nav kernel's matrices live there while it runs: a global array read back
    right after it was written is an L2 round trip (~200 cycles), which made the interval's chain of dependent 3×3
    products latency-bound (0.3–0.4 ms on an H100 for 10 samples, 35 µs a sample)."""
    ...


@wp.func
def get_blk(a: wp.array3d(dtype=wp.mat33d), b: int, r: int, c: int, at: int, ncol: int, sh: int) -> wp.mat33d:
    """Block (r, c) of filter b's matrix: from the shared slots at ``at`` (``ncol`` blocks a row) when ``sh``, else
    from the global array."""
    if sh == 0:
        return a[b, r, c]
    o = at + 9 * (r * ncol + c)
    z = wp.float64(0.0)
    return wp.mat33d(shared_slot(o, z, 0), shared_slot(o + 1, z, 0), shared_slot(o + 2, z, 0),
                     shared_slot(o + 3, z, 0), shared_slot(o + 4, z, 0), shared_slot(o + 5, z, 0),
                     shared_slot(o + 6, z, 0), shared_slot(o + 7, z, 0), shared_slot(o + 8, z, 0))


@wp.func
def put_blk(a: wp.array3d(dtype=wp.mat33d), b: int, r: int, c: int, at: int, ncol: int, sh: int, m: wp.mat33d):
    """Write block (r, c) (see :func:`get_blk`)."""
    if sh == 0:
        a[b, r, c] = m
    else:
        o = at + 9 * (r * ncol + c)
        for i in range(3):
            for j in range(3):
                shared_slot(o + 3 * i + j, m[i, j], 1)


@wp.func
def get_f64(a: wp.array3d(dtype=wp.float64), b: int, i: int, j: int, sh: int) -> wp.float64:
    """Entry (i, j) of filter b's 15×15 Cholesky scratch (shared slots when ``sh``)."""
    return scratch_f64(a, b, 15 * i + j, sh)


@wp.func
def put_f64(a: wp.array3d(dtype=wp.float64), b: int, i: int, j: int, sh: int, v: wp.float64):
    scratch_put(a, b, 15 * i + j, sh, v)


@wp.func
def trailing_update(a: wp.array3d(dtype=wp.float64), b: int, ii: int, kk: int, jj: int, sh: int):
    """Right-looking Cholesky: column jj's term off element (ii, kk) of the trailing lower triangle (the same operations
    in the same order as a left-looking column's dot product)."""
    put_f64(a, b, ii, kk, sh, get_f64(a, b, ii, kk, sh) - get_f64(a, b, ii, jj, sh) * get_f64(a, b, kk, jj, sh))


@wp.func
def scratch_f64(a: wp.array3d(dtype=wp.float64), b: int, o: int, sh: int) -> wp.float64:
    """Float64 ``o`` (row-major) of filter b's 15×15 scratch: the shared slots at :data:`CHOL_AT` when ``sh``, else
    ``chol_scratch``. The Cholesky uses it at the interval's end, the steps before as blocks (:func:`w_get`)."""
    if sh == 0:
        return a[b, o // 15, o % 15]
    return shared_slot(CHOL_AT + o, wp.float64(0.0), 0)


@wp.func
def scratch_put(a: wp.array3d(dtype=wp.float64), b: int, o: int, sh: int, v: wp.float64):
    if sh == 0:
        a[b, o // 15, o % 15] = v
    else:
        shared_slot(CHOL_AT + o, v, 1)


@wp.func
def p_get(a: wp.array3d(dtype=wp.mat33d), b: int, r: int, c: int, sh: int) -> wp.mat33d:
    """Block (r, c) of P (4×4 blocks; :func:`get_blk`)."""
    return get_blk(a, b, r, c, COV_AT, 4, sh)


@wp.func
def p_put(a: wp.array3d(dtype=wp.mat33d), b: int, r: int, c: int, sh: int, m: wp.mat33d):
    put_blk(a, b, r, c, COV_AT, 4, sh, m)


@wp.func
def phi_get(a: wp.array3d(dtype=wp.mat33d), b: int, r: int, c: int, sh: int) -> wp.mat33d:
    """Block (r, c) of Φ (5×5 blocks)."""
    return get_blk(a, b, r, c, PHI_AT, 5, sh)


@wp.func
def phi_put(a: wp.array3d(dtype=wp.mat33d), b: int, r: int, c: int, sh: int, m: wp.mat33d):
    put_blk(a, b, r, c, PHI_AT, 5, sh, m)


@wp.func
def s_get(a: wp.array3d(dtype=wp.mat33d), b: int, r: int, c: int, sh: int) -> wp.mat33d:
    """Block (r, c) of S (5×5 blocks)."""
    return get_blk(a, b, r, c, NOISE_AT, 5, sh)


@wp.func
def s_put(a: wp.array3d(dtype=wp.mat33d), b: int, r: int, c: int, sh: int, m: wp.mat33d):
    put_blk(a, b, r, c, NOISE_AT, 5, sh, m)


@wp.func
def ps_get(phi: wp.array3d(dtype=wp.mat33d), noise: wp.array3d(dtype=wp.mat33d), which: int, b: int, r: int, c: int,
           sh: int) -> wp.mat33d:
    """Block (r, c) of Φ (``which`` = 0) or S (1); in shared memory the choice is an offset, not a branch."""
    if sh == 1 or which == 0:
        return get_blk(phi, b, r, c, PHI_AT + which * (NOISE_AT - PHI_AT), 5, sh)
    return get_blk(noise, b, r, c, NOISE_AT, 5, sh)


@wp.func
def ps_put(phi: wp.array3d(dtype=wp.mat33d), noise: wp.array3d(dtype=wp.mat33d), which: int, b: int, r: int, c: int,
           sh: int, m: wp.mat33d):
    if sh == 1 or which == 0:
        put_blk(phi, b, r, c, PHI_AT + which * (NOISE_AT - PHI_AT), 5, sh, m)
    else:
        put_blk(noise, b, r, c, NOISE_AT, 5, sh, m)


@wp.func
def w_get(a: wp.array3d(dtype=wp.float64), b: int, idx: int, sh: int) -> wp.mat33d:
    """Block ``idx`` of the step scratch (the 15×15 scratch's slots as 25 blocks: ``W_Q`` ...)."""
    o = 9 * idx
    return wp.mat33d(scratch_f64(a, b, o, sh), scratch_f64(a, b, o + 1, sh), scratch_f64(a, b, o + 2, sh),
                     scratch_f64(a, b, o + 3, sh), scratch_f64(a, b, o + 4, sh), scratch_f64(a, b, o + 5, sh),
                     scratch_f64(a, b, o + 6, sh), scratch_f64(a, b, o + 7, sh), scratch_f64(a, b, o + 8, sh))


@wp.func
def w_put(a: wp.array3d(dtype=wp.float64), b: int, idx: int, sh: int, m: wp.mat33d):
    for i in range(3):
        for j in range(3):
            scratch_put(a, b, 9 * idx + 3 * i + j, sh, m[i, j])


@wp.func
def lp_get(cov: wp.array3d(dtype=wp.mat33d), work: wp.array3d(dtype=wp.float64), b: int, r: int, c: int,
           sh: int) -> wp.mat33d:
    """Block (r, c) of ``A^l P``: rows 0–1 from the scratch (``W_Q``), rows 2–3 are P's (``A^l`` leaves them)."""
    if r < 2:
        return w_get(work, b, W_Q + 4 * r + c, sh)
    return p_get(cov, b, r, c, sh)


@wp.func
def gain_blk(work: wp.array3d(dtype=wp.float64), b: int, k: int, sh: int) -> wp.mat33d:
    """Block k of ``G = [I; L_k N_k⁻¹ ...]`` (k = 0: the identity; 1..4: the gains of dv, dθ, dba, dbg)."""
    if k == 0:
        return wp.identity(n=3, dtype=wp.float64)
    return w_get(work, b, W_GAIN + k - 1, sh)


@wp.func
def step_terms(imu: wp.array3d(dtype=wp.vec3d), b: int, k: int, q: wp.vec4d, ba: wp.vec3d, bg: wp.vec3d,
               work: wp.array3d(dtype=wp.float64), sh: int):
    """The transition blocks of step k from the nominal state before it (attitude ``q``, biases ``ba``, ``bg``):
    ``A = -R [a]x dt``, ``B = -R dt``, ``E = Exp(w dt)ᵀ``, ``J = -J_r(w dt) dt``, into the scratch's
    ``W_TERMS + 4 (k % 2)`` (two steps alternate: the lanes read step k's while the nominal lane forms step k + 1's)."""
    half = wp.float64(0.5)
    eye = wp.identity(n=3, dtype=wp.float64)
    dt = imu[b, k, 2][0]
    rot = rot_d(q)
    wdt = (imu[b, k, 1] - bg) * dt
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
    at = W_TERMS + 4 * (k % 2)
    w_put(work, b, at, sh, -(rot * skew_d(imu[b, k, 0] - ba)) * dt)
    w_put(work, b, at + 1, sh, -rot * dt)
    w_put(work, b, at + 2, sh, wp.transpose(eye + c1 * kx + c2 * kk))
    w_put(work, b, at + 3, sh, -(eye - j1 * kx + j2 * kk) * dt)


@wp.func
def p_times_an(a: wp.array3d(dtype=wp.mat33d), b: int, r: int, sh: int, dt: wp.float64, am: wp.mat33d,
               bm: wp.mat33d) -> wp.mat33d:
    """Block row r of ``P A^nᵀ``: ``dt P_r0 + dt/2 (P_r1 Aᵀ + P_r2 Bᵀ)``."""
    return dt * p_get(a, b, r, 0, sh) + wp.float64(0.5) * dt * (p_get(a, b, r, 1, sh) * wp.transpose(am)
                                                               + p_get(a, b, r, 2, sh) * wp.transpose(bm))


def _nav_interval(tiled: bool):
    @wp.kernel
    def nav_interval_kernel(
        row0: int,
        begin: int,
        finish: int,
        keep: int,
        progress: wp.array2d(dtype=wp.float64),
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
        """Filter ``b = row0 + t``: K = ``counts[b, INT_STEPS]`` IMU samples (specific force ``imu[b, k, 0]``, body
        rate ``imu[b, k, 1]``, step length ``imu[b, k, 2][0]`` in s; ``nominal_dt`` is the step the noise terms are
        given for): advances its nominal state and ``cov`` (P, 4×4 blocks) in place; writes Φ and the lower Cholesky
        factor of S (5×5 blocks, float32), the nominal pose ``[p (3), q (4)]`` at the end of the interval, and what
        the update's kernels read of P: ``P_θθ`` (``att_cov_out``) and the column blocks ``P_:θ`` (``p_col_out``).
        ``q_lin`` = diagonal of Q^l per block (dv, dth, dba, dbg); ``q_pos[b]`` = diagonal of Q^n (the position noise
        the Kalman part models, in N_k and L_k); ``q_rough`` = per-step variance of the roughening, added to the
        particles' dp only (``S_dpdp += K q_rough I``: T_k leaves a dp-only noise on dp), so that L_k never reads it
        as velocity. ``q_vel_down[b]`` is added to the down velocity's Q^l (a map-error offset's change along the track,
        :meth:`warptan.sensing.likelihood.Likelihood.offset_process`; 0 without one).

        An interval may run as several launches, each taking the samples buffered since the last (``progress[b]`` =
        [samples done, Σ dt_k / dt] so far; ``counts`` the samples buffered): ``begin`` starts the interval (Φ = I,
        S = 0, nothing done), else Φ and S are read back from ``phi`` and ``noise``; ``keep`` leaves Φ and S there
        for a later launch; ``finish`` writes the outputs of the interval as it stands (without changing Φ, S or P:
        a later launch may go on from them). Float64 all through: the same bits as one launch.

        Tiled (CUDA): P, Φ, S and the Cholesky scratch live in the block's shared memory (:func:`shared_slot`); the
        lanes share each phase's independent pieces (a block column, a block row, one block, one row of the
        Cholesky; :func:`span`), a warp of its own forms the gains, one lane advances the nominal state and forms the
        next step's transition blocks (:data:`NAV_BLOCK_DIM`), and :func:`block_sync` separates the phases. On the
        CPU one thread does every piece in the same order: each block sees the same operations in either form."""
        if wp.static(tiled):
            t, lane = wp.tid()
            sh = 1
        else:
            t = wp.tid()
            lane = 0
            sh = 0
        nominal = lane == NOMINAL_LANE or sh == 0  # the lane that holds the nominal state (the CPU's one thread)
        b = row0 + t
        if wp.static(tiled):  # P into the block's shared slots (lane 4 r + c: block (r, c)), back at the end
            if lane < 16:
                p_put(cov, b, lane // 4, lane % 4, sh, cov[b, lane // 4, lane % 4])
        zero = wp.mat33d()
        eye = wp.identity(n=3, dtype=wp.float64)
        half = wp.float64(0.5)
        i0, i1 = span(sh, lane, 0, 25)
        for idx in range(i0, i1):
            r = idx // 5
            c = idx % 5
            if begin != 0:
                s_put(noise, b, r, c, sh, zero)
                if r == c:
                    phi_put(phi, b, r, c, sh, eye)
                else:
                    phi_put(phi, b, r, c, sh, zero)
            elif sh != 0:  # the interval so far, into the shared slots
                s_put(noise, b, r, c, sh, noise[b, r, c])
                phi_put(phi, b, r, c, sh, phi[b, r, c])
        p = pos[b]
        v = vel[b]
        q = quat[b]
        ba = accel_bias[b]
        bg = gyro_bias[b]
        n_steps = counts[b, INT_STEPS]
        k0 = int(0)
        steps = wp.float64(0.0)  # Σ dt_k / dt: the interval in nominal steps (n_steps when evenly spaced)
        if begin == 0:
            k0 = int(progress[b, 0])
            steps = progress[b, 1]
        if nominal and k0 < n_steps:
            step_terms(imu, b, k0, q, ba, bg, chol_scratch, sh)
        for k in range(k0, n_steps):
            dt = imu[b, k, 2][0]
            scale = dt / nominal_dt  # exactly 1 for a nominal step: the same bits as a fixed step
            steps = steps + scale
            block_sync()  # the previous step's P and S are written, and this step's transition blocks
            at = W_TERMS + 4 * (k % 2)
            a = w_get(chol_scratch, b, at, sh)
            bm = w_get(chol_scratch, b, at + 1, sh)
            e = w_get(chol_scratch, b, at + 2, sh)
            jm = w_get(chol_scratch, b, at + 3, sh)
            # ---- Riccati (P in 4×4 blocks: dv, dth, dba, dbg). A^l P by block columns (its rows 0–1 into the
            # scratch: P itself is still read), Φ <- T Φ and S <- T S by columns (pieces 0..4 Φ's, 5..9 S's),
            # P A^nᵀ by block rows, and the nominal state's step
            i0, i1 = span(sh, lane, 0, 4)
            for c in range(i0, i1):
                y0, y1 = apply_l(p_get(cov, b, 0, c, sh), p_get(cov, b, 1, c, sh), p_get(cov, b, 2, c, sh),
                                 p_get(cov, b, 3, c, sh), a, bm, e, jm)
                w_put(chol_scratch, b, W_Q + c, sh, y0)
                w_put(chol_scratch, b, W_Q + 4 + c, sh, y1)
            i0, i1 = span(sh, lane - SIDE_LANE, 0, 10)
            for idx in range(i0, i1):
                which = idx // 5
                c = idx % 5
                y0, y1, y2 = apply_t(ps_get(phi, noise, which, b, 0, c, sh), ps_get(phi, noise, which, b, 1, c, sh),
                                     ps_get(phi, noise, which, b, 2, c, sh), ps_get(phi, noise, which, b, 3, c, sh),
                                     ps_get(phi, noise, which, b, 4, c, sh), dt, a, bm, e, jm)
                ps_put(phi, noise, which, b, 0, c, sh, y0)
                ps_put(phi, noise, which, b, 1, c, sh, y1)
                ps_put(phi, noise, which, b, 2, c, sh, y2)
            i0, i1 = span(sh, lane - GAIN_LANE, 0, 4)
            for r in range(i0, i1):
                w_put(chol_scratch, b, W_PA + r, sh, p_times_an(cov, b, r, sh, dt, a, bm))
            if nominal:  # the mechanization (warptan.nav.ins._step_inplace)
                rot = rot_d(q)
                wdt = (imu[b, k, 1] - bg) * dt
                an = rot * (imu[b, k, 0] - ba) + wp.vec3d(wp.float64(0.0), wp.float64(0.0), wp.float64(GRAVITY_D))
                p = p + v * dt + half * dt * dt * an
                v = v + an * dt
                q = quat_mul_exp_d(q, wdt)
            block_sync()
            # (A^l P) A^lᵀ by block rows (transposed) into P, S <- S Tᵀ by rows; N_k = A^n P A^nᵀ + Q^n and the gains
            # L_k N_k⁻¹ (piece 0: dv, 1: dθ) and (P A^nᵀ)_r N_k⁻¹ (2: dba, 3: dbg); the next step's blocks
            i0, i1 = span(sh, lane, 0, 4)
            for r in range(i0, i1):
                y0, y1 = apply_l(wp.transpose(lp_get(cov, chol_scratch, b, r, 0, sh)),
                                 wp.transpose(lp_get(cov, chol_scratch, b, r, 1, sh)),
                                 wp.transpose(lp_get(cov, chol_scratch, b, r, 2, sh)),
                                 wp.transpose(lp_get(cov, chol_scratch, b, r, 3, sh)), a, bm, e, jm)
                p_put(cov, b, r, 0, sh, wp.transpose(y0))
                p_put(cov, b, r, 1, sh, wp.transpose(y1))
                if r < 2:
                    p_put(cov, b, r, 2, sh, lp_get(cov, chol_scratch, b, r, 2, sh))
                    p_put(cov, b, r, 3, sh, lp_get(cov, chol_scratch, b, r, 3, sh))
            i0, i1 = span(sh, lane - SIDE_LANE, 0, 5)
            for r in range(i0, i1):
                y0, y1, y2 = apply_t(wp.transpose(s_get(noise, b, r, 0, sh)), wp.transpose(s_get(noise, b, r, 1, sh)),
                                     wp.transpose(s_get(noise, b, r, 2, sh)), wp.transpose(s_get(noise, b, r, 3, sh)),
                                     wp.transpose(s_get(noise, b, r, 4, sh)), dt, a, bm, e, jm)
                s_put(noise, b, r, 0, sh, wp.transpose(y0))
                s_put(noise, b, r, 1, sh, wp.transpose(y1))
                s_put(noise, b, r, 2, sh, wp.transpose(y2))
            i0, i1 = span(sh, lane - GAIN_LANE, 0, 4)
            if i0 < i1:  # (a lane of the gains' warp forms N_k, its inverse and L_k; the CPU's thread once)
                pa0 = w_get(chol_scratch, b, W_PA, sh)
                pa1 = w_get(chol_scratch, b, W_PA + 1, sh)
                pa2 = w_get(chol_scratch, b, W_PA + 2, sh)
                pa3 = w_get(chol_scratch, b, W_PA + 3, sh)
                nk = sym_d(dt * pa0 + half * dt * (a * pa1 + bm * pa2) + (q_pos[b] * scale) * eye)
                l0, l1 = apply_l(pa0, pa1, pa2, pa3, a, bm, e, jm)
                inv_nk = wp.inverse(nk)
                for r in range(i0, i1):
                    gain = pa3
                    if r == 0:
                        gain = l0
                        w_put(chol_scratch, b, W_NK, sh, nk)
                    elif r == 1:
                        gain = l1
                    elif r == 2:
                        gain = pa2
                    w_put(chol_scratch, b, W_GAIN + r, sh, gain * inv_nk)
            if nominal and k + 1 < n_steps:
                step_terms(imu, b, k + 1, q, ba, bg, chol_scratch, sh)
            block_sync()
            # P += - L N Lᵀ + Q^l (block (r, c): piece 4 r + c); S += G N Gᵀ, G = [I; L] (piece 5 r + c)
            i0, i1 = span(sh, lane, 0, 16)
            for idx in range(i0, i1):
                r = idx // 4
                c = idx % 4
                gn = gain_blk(chol_scratch, b, r + 1, sh) * w_get(chol_scratch, b, W_NK, sh)
                m = p_get(cov, b, r, c, sh) - gn * wp.transpose(gain_blk(chol_scratch, b, c + 1, sh))
                if r == c:
                    m = m + (q_lin[r] * scale) * eye
                    if r == 0 and q_vel_down[b] > wp.float64(0.0):
                        m[2, 2] = m[2, 2] + q_vel_down[b] * scale
                p_put(cov, b, r, c, sh, m)
            i0, i1 = span(sh, lane - SIDE_LANE, 0, 25)
            for idx in range(i0, i1):
                r = idx // 5
                c = idx % 5
                gn = gain_blk(chol_scratch, b, r, sh) * w_get(chol_scratch, b, W_NK, sh)
                s_put(noise, b, r, c, sh, s_get(noise, b, r, c, sh) + gn * wp.transpose(gain_blk(chol_scratch, b, c,
                                                                                                   sh)))
            block_sync()
            # P symmetrised (piece 4 r + c, r ≤ c, writes both of a pair)
            i0, i1 = span(sh, lane, 0, 16)
            for idx in range(i0, i1):
                r = idx // 4
                c = idx % 4
                if r == c:
                    p_put(cov, b, r, r, sh, sym_d(p_get(cov, b, r, r, sh)))
                elif r < c:
                    m = half * (p_get(cov, b, r, c, sh) + wp.transpose(p_get(cov, b, c, r, sh)))
                    p_put(cov, b, r, c, sh, m)
                    p_put(cov, b, c, r, sh, wp.transpose(m))
        if nominal:
            pos[b] = p
            vel[b] = v
            quat[b] = q
            progress[b, 0] = wp.float64(n_steps)
            progress[b, 1] = steps
        if wp.static(tiled):
            if keep != 0:  # the interval may go on at a later launch: Φ, S (and P) back to global memory
                block_sync()
                i0, i1 = span(sh, lane, 0, 25)
                for idx in range(i0, i1):
                    phi[b, idx // 5, idx % 5] = phi_get(phi, b, idx // 5, idx % 5, sh)
                    noise[b, idx // 5, idx % 5] = s_get(noise, b, idx // 5, idx % 5, sh)
                if lane < 16:
                    cov[b, lane // 4, lane % 4] = p_get(cov, b, lane // 4, lane % 4, sh)
        if finish == 0:
            return
        if nominal:
            for i in range(3):
                pose_out[b, i] = p[i]
            for i in range(4):
                pose_out[b, 3 + i] = q[i]
        block_sync()
        # ---- outputs: Φ (float32) and chol(S), scalar Cholesky on a 15×15 scratch (semi-definite safe); the
        # roughening's dp-only noise joins S's first block here (S itself stays as the samples left it)
        rough = steps * q_rough * eye
        i0, i1 = span(sh, lane, 0, 25)
        for idx in range(i0, i1):
            r = idx // 5
            c = idx % 5
            phi_out[b, r, c] = wp.mat33(phi_get(phi, b, r, c, sh))
            s_rc = s_get(noise, b, r, c, sh)
            s_cr = s_get(noise, b, c, r, sh)
            if r == 0 and c == 0:
                s_rc = s_rc + rough
                s_cr = s_rc
            blk = half * (s_rc + wp.transpose(s_cr))
            for i in range(3):
                for j in range(3):
                    put_f64(chol_scratch, b, 3 * r + i, 3 * c + j, sh, blk[i, j])
        i0, i1 = span(sh, lane, 0, 4)
        for r in range(i0, i1):
            p_col_out[b, r] = wp.mat33(p_get(cov, b, r, 1, sh))
            if r == 1:
                att_cov_out[b] = wp.mat33(p_get(cov, b, 1, 1, sh))
        for jj in range(15):  # column jj, right-looking: the columns before it already took their terms off
            block_sync()
            dd = get_f64(chol_scratch, b, jj, jj, sh)
            if dd > wp.float64(1.0e-30):
                dd = wp.sqrt(dd)
            else:
                dd = wp.float64(0.0)
            i0, i1 = span(sh, lane, jj + 1, 15)  # piece ii: row ii of the column
            for ii in range(i0, i1):
                if dd > wp.float64(0.0):
                    put_f64(chol_scratch, b, ii, jj, sh, get_f64(chol_scratch, b, ii, jj, sh) / dd)
                else:
                    put_f64(chol_scratch, b, ii, jj, sh, wp.float64(0.0))
            i0, i1 = span(sh, lane, 0, jj)
            for i2 in range(i0, i1):
                put_f64(chol_scratch, b, i2, jj, sh, wp.float64(0.0))
            block_sync()
            if lane == 0:
                put_f64(chol_scratch, b, jj, jj, sh, dd)
            # the column's term off the trailing lower triangle: piece t its element (ii, kk), jj < kk <= ii
            if sh == 0:  # (the CPU's one thread: the elements in order)
                for ii in range(jj + 1, 15):
                    for kk in range(jj + 1, ii + 1):
                        trailing_update(chol_scratch, b, ii, kk, jj, sh)
            else:  # lane t: element t of the triangle's rows (at most 105 <= NAV_BLOCK_DIM)
                nn = 14 - jj
                if lane < nn * (nn + 1) // 2:
                    rr = int((wp.sqrt(float(8 * lane + 1)) - 1.0) * 0.5)  # (exact for these small integers)
                    trailing_update(chol_scratch, b, jj + 1 + rr, jj + 1 + lane - rr * (rr + 1) // 2, jj, sh)
        block_sync()
        i0, i1 = span(sh, lane, 0, 25)
        for idx in range(i0, i1):
            r = idx // 5
            c = idx % 5
            lo = wp.mat33d()
            for i in range(3):
                for j in range(3):
                    lo[i, j] = get_f64(chol_scratch, b, 3 * r + i, 3 * c + j, sh)
            chol_out[b, r, c] = wp.mat33(lo)
        if wp.static(tiled):
            if lane < 16:
                cov[b, lane // 4, lane % 4] = p_get(cov, b, lane // 4, lane % 4, sh)

    return nav_interval_kernel


nav_interval_kernels = {tiled: _nav_interval(tiled) for tiled in (True, False)}
"""The interval kernel: ``[True]`` one CUDA block of :data:`NAV_BLOCK_DIM` threads per filter
(``wp.launch_tiled``), ``[False]`` one thread per filter (the CPU, whose launches are split across cores)."""
nav_interval_kernel = nav_interval_kernels[False]
assert NAV_SHARED_SLOTS == CHOL_AT + 15 * 15, "the slots of nav_slots (shared_slot's snippet) must hold P, Φ, S, chol"
