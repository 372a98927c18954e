"""What the host reads of a filter at once (:meth:`~warptan.filter.mpf.MarginalizedParticleFilter.estimate`): the
particles' weighted moments and, packed with them into one row per filter for one device-to-host copy, P's blocks
and the nominal INS."""

import warp as wp

from warptan.kernels.filter.common import (
    MOM_DP,
    MOM_DPDP,
    MOM_L,
    MOM_LL,
    MOM_W,
    N_MOMENT_CHUNKS,
    N_MOMENTS,
    NOM_BA,
    NOM_BG,
    NOM_POS,
    NOM_QUAT,
    NOM_VEL,
    chunk_span,
    vec12,
)

wp.set_module_options({"enable_backward": False})


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
    lo, hi = chunk_span(c, n_per, N_MOMENT_CHUNKS)
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


@wp.func
def combined(partial_in: wp.array3d(dtype=wp.float64), b: int, k: int) -> wp.float64:
    """Moment k of filter b: its chunks' partial sums added in order."""
    s = wp.float64(0.0)
    for c in range(partial_in.shape[1]):
        s += partial_in[b, c, k]
    return s


RO_COV = wp.constant(N_MOMENTS)
"""Column of :data:`readout_kernel`'s row where the 16 blocks of P begin (``P_ij[r, c]`` at
``RO_COV + 9 (4 i + j) + 3 r + c``: the host's ``(4, 4, 3, 3)`` layout); columns ``[0, N_MOMENTS)`` are the moments
(:data:`moment_partials_kernel`)."""
RO_NOMINAL = wp.constant(N_MOMENTS + 144)
"""Column where the nominal INS begins (``N_NOMINAL`` values in the ``NOM_*`` layout)."""
N_READOUT = wp.constant(N_MOMENTS + 144 + 16)
"""Columns of a read-out row."""


@wp.kernel
def readout_kernel(
    partial_in: wp.array3d(dtype=wp.float64),
    cov: wp.array3d(dtype=wp.mat33d),
    pos: wp.array(dtype=wp.vec3d),
    vel: wp.array(dtype=wp.vec3d),
    quat: wp.array(dtype=wp.vec4d),
    accel_bias: wp.array(dtype=wp.vec3d),
    gyro_bias: wp.array(dtype=wp.vec3d),
    out: wp.array2d(dtype=wp.float64),
):
    """One thread per (filter b, column k) of what an estimate reads, packed into one row for one device-to-host copy:
    the particles' moments (:func:`combined` sums of :data:`moment_partials_kernel`'s chunks), P's blocks
    (:data:`RO_COV`) and the nominal INS (:data:`RO_NOMINAL`)."""
    b, k = wp.tid()
    if k < RO_COV:
        out[b, k] = combined(partial_in, b, k)
    elif k < RO_NOMINAL:
        e = k - RO_COV
        m = e // 9
        out[b, k] = cov[b, m // 4, m % 4][(e % 9) // 3, e % 3]
    else:
        j = k - RO_NOMINAL
        if j < NOM_VEL:
            out[b, k] = pos[b][j - NOM_POS]
        elif j < NOM_QUAT:
            out[b, k] = vel[b][j - NOM_VEL]
        elif j < NOM_BA:
            out[b, k] = quat[b][j - NOM_QUAT]
        elif j < NOM_BG:
            out[b, k] = accel_bias[b][j - NOM_BA]
        else:
            out[b, k] = gyro_bias[b][j - NOM_BG]
