"""Rotation math: host round trips and the @wp.func versions against NumPy on every device (design notes §1)."""

import numpy as np
import pytest
import warp as wp

from warptan import frames
from warptan.kernels import frames as kframes


def _random_quats(n, seed):
    q = np.random.default_rng(seed).normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_euler_matrix_quaternion_round_trips():
    """quat -> matrix -> quat and Euler -> quat -> Euler invert each other (ZYX, pitch within ±90°)."""
    q = _random_quats(500, 0)
    q2 = frames.mat_to_quat(frames.quat_to_mat(q))
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", q, q2)), 1.0, atol=1e-12)
    rng = np.random.default_rng(1)
    eul = np.stack([rng.uniform(-np.pi, np.pi, 500), rng.uniform(-1.5, 1.5, 500), rng.uniform(-np.pi, np.pi, 500)], 1)
    np.testing.assert_allclose(frames.quat_to_euler(frames.euler_to_quat(*eul.T)), eul, atol=1e-10)


def test_euler_convention_is_zyx():
    """R(roll, pitch, yaw) = Rz(yaw) Ry(pitch) Rx(roll), and R maps body to navigation vectors."""
    r, p, y = 0.3, -0.2, 1.1
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    np.testing.assert_allclose(frames.euler_to_mat(r, p, y), rz @ ry @ rx, atol=1e-14)
    # yaw 90°: the body's forward axis points east
    np.testing.assert_allclose(frames.euler_to_mat(0, 0, np.pi / 2) @ [1, 0, 0], [0, 1, 0], atol=1e-15)


def test_exp_log_and_skew():
    """Log(Exp(phi)) = phi for |phi| < π, Exp composes like matrices, skew(a) b = a × b."""
    rng = np.random.default_rng(2)
    phi = rng.normal(size=(300, 3))
    phi *= (rng.uniform(0, 3.1, 300) / np.linalg.norm(phi, axis=1))[:, None]
    np.testing.assert_allclose(frames.quat_log(frames.quat_exp(phi)), phi, atol=1e-12)
    np.testing.assert_allclose(frames.quat_log(frames.quat_exp(1e-10 * phi)), 1e-10 * phi, atol=1e-22)
    a, b = _random_quats(1, 3)[0], frames.quat_exp(phi[0])
    np.testing.assert_allclose(frames.quat_to_mat(frames.quat_mul(a, b)),
                               frames.quat_to_mat(a) @ frames.quat_to_mat(b), atol=1e-14)
    v, w = rng.normal(size=(2, 3))
    np.testing.assert_allclose(frames.skew(v) @ w, np.cross(v, w), atol=1e-15)


@pytest.mark.parametrize("bad", [[1, 0, 0], [0, 0, 0, 0], [1, 0, 0, np.nan], [0.9, 0, 0, 0]])
def test_check_unit_quat_rejects(bad):
    """Non-unit, zero, short or non-finite quaternions are rejected."""
    with pytest.raises(ValueError, match="quaternion"):
        frames.check_unit_quat(bad)


def test_wp_funcs_match_numpy(device):
    """kernels.frames quat_to_mat and q ⊗ Exp(phi) equal the float64 NumPy functions to float32 precision."""
    q = _random_quats(1000, 4)
    phi = np.random.default_rng(5).normal(scale=0.3, size=(1000, 3))
    phi[:10] *= 1e-8  # the small-angle branch
    q_d = wp.array(q.astype(np.float32), dtype=wp.vec4, device=device)
    mats = wp.empty(1000, dtype=wp.mat33, device=device)
    wp.launch(kframes.quat_to_mat_kernel, dim=1000, inputs=[q_d], outputs=[mats], device=device)
    np.testing.assert_allclose(mats.numpy(), frames.quat_to_mat(q), atol=2e-6)
    out = wp.empty(1000, dtype=wp.vec4, device=device)
    wp.launch(kframes.quat_mul_exp_kernel, dim=1000, inputs=[q_d, wp.array(phi.astype(np.float32), dtype=wp.vec3,
              device=device)], outputs=[out], device=device)
    np.testing.assert_allclose(out.numpy(), frames.quat_mul(q, frames.quat_exp(phi)), atol=2e-6)
