"""The particles' moves: initial draw, one measurement interval (``Φ x + C z``) and each particle's pose."""

import warp as wp

from warptan.kernels.filter.common import gaussian3, gaussian_blocks, vec12
from warptan.kernels.frames import quat_exp_wxyz, quat_mul_wxyz

wp.set_module_options({"enable_backward": False})

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
    """One measurement interval of every particle (design notes §6 steps 3–4 over its K IMU steps, composed by
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
def nominal_pose(pose: wp.array2d(dtype=wp.float64), b: int):
    """Filter b's nominal pose as :func:`pose_at` takes it: position (float64), attitude quaternion (float32)."""
    return (wp.vec3d(pose[b, 0], pose[b, 1], pose[b, 2]),
            wp.vec4(wp.float32(pose[b, 3]), wp.float32(pose[b, 4]), wp.float32(pose[b, 5]), wp.float32(pose[b, 6])))


@wp.func
def pose_at(p_nom: wp.vec3d, q_nom: wp.vec4, d: wp.vec3, lm: vec12):
    """:func:`pose_of_particle` of a particle given by value, its filter's nominal pose at hand (:func:`nominal_pose`):
    (position, attitude)."""
    p = wp.vec3(wp.float32(p_nom[0] + wp.float64(d[0])), wp.float32(p_nom[1] + wp.float64(d[1])),
                wp.float32(p_nom[2] + wp.float64(d[2])))
    return p, wp.normalize(quat_mul_wxyz(q_nom, quat_exp_wxyz(wp.vec3(lm[3], lm[4], lm[5]))))


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
    p_nom, q_nom = nominal_pose(pose, i // n_per)
    p, q = pose_at(p_nom, q_nom, dp[i], lin[i])
    pos_out[i] = p
    quat_out[i] = q


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
