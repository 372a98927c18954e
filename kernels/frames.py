"""Rotation math for kernels (design notes §1): Hamilton quaternions stored scalar-first as ``wp.vec4`` [w, x, y, z].

Warp's own ``wp.quat`` is scalar-last; these functions take and return the project's scalar-first
``vec4`` so that device arrays match the host arrays of :mod:`warptan.nav.frames` element for element.
``q = q_nb``; :func:`quat_to_mat_wxyz` maps body vectors to the navigation frame (``v_n = R(q) v_b``).
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func
def quat_to_mat_wxyz(q: wp.vec4) -> wp.mat33:
    """Rotation matrix ``R(q)`` (body to navigation) of a unit quaternion [w, x, y, z]."""
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def quat_mul_wxyz(a: wp.vec4, b: wp.vec4) -> wp.vec4:
    """Hamilton product ``a ⊗ b`` of scalar-first quaternions."""
    return wp.vec4(
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    )


@wp.func
def quat_exp_wxyz(phi: wp.vec3) -> wp.vec4:
    """``Exp(phi)``: the unit quaternion of rotation vector ``phi`` (rad), scalar first."""
    angle = wp.length(phi)
    if angle < 1.0e-6:
        # second-order series, exact to float32 precision below 1e-6 rad
        return wp.normalize(wp.vec4(1.0 - 0.125 * angle * angle, 0.5 * phi[0], 0.5 * phi[1], 0.5 * phi[2]))
    s = wp.sin(0.5 * angle) / angle
    return wp.vec4(wp.cos(0.5 * angle), s * phi[0], s * phi[1], s * phi[2])


@wp.func
def quat_log_wxyz(q: wp.vec4) -> wp.vec3:
    """``Log(q)``: the rotation vector (rad, the short way round) of a unit quaternion, scalar first."""
    sgn = 1.0
    if q[0] < 0.0:
        sgn = -1.0
    w = sgn * q[0]
    v = sgn * wp.vec3(q[1], q[2], q[3])
    vn = wp.length(v)
    if vn < 1.0e-7:
        return (2.0 / w) * v
    return (2.0 * wp.atan2(vn, w) / vn) * v


@wp.kernel
def quat_to_mat_kernel(q_in: wp.array(dtype=wp.vec4), mat_out: wp.array(dtype=wp.mat33)):
    """One thread per quaternion: ``R(q)``."""
    k = wp.tid()
    mat_out[k] = quat_to_mat_wxyz(q_in[k])


@wp.kernel
def quat_mul_exp_kernel(
    q_in: wp.array(dtype=wp.vec4), phi_in: wp.array(dtype=wp.vec3), q_out: wp.array(dtype=wp.vec4)
):
    """One thread per pair: ``q ⊗ Exp(phi)``."""
    k = wp.tid()
    q_out[k] = quat_mul_wxyz(q_in[k], quat_exp_wxyz(phi_in[k]))
