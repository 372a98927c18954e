"""Rotation math on the host, float64 NumPy (design notes §1; Solà 2017 §2–4 for Exp/Log).

Quaternions are Hamilton, scalar first ``[w, x, y, z]``, ``q = q_nb``; ``quat_to_mat(q)`` maps body to
navigation vectors. Euler angles are ZYX: ``R = Rz(yaw) Ry(pitch) Rx(roll)``, returned/accepted as
``(roll, pitch, yaw)`` in radians. Every function accepts a single item or a stack (leading axes).
The matching device functions are in :mod:`warptan.kernels.frames`.
"""

from __future__ import annotations

import numpy as np

from warptan.checks import FilterError

UNIT_TOL = 1e-6
"""How far from 1 a quaternion's norm may be before :func:`check_unit_quat` rejects it."""


def check_unit_quat(q, name: str = "quaternion") -> np.ndarray:
    """Return ``q`` as float64 (..., 4) after checking it is finite and of unit norm."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape[-1:] != (4,):
        raise FilterError(f"{name} must have 4 components [w, x, y, z], got shape {q.shape}")
    if not np.isfinite(q).all():
        raise FilterError(f"{name} has non-finite components: {q}")
    norm = np.linalg.norm(q, axis=-1)
    if np.any(np.abs(norm - 1.0) > UNIT_TOL):
        raise FilterError(f"{name} is not a unit quaternion (norm {norm.min():.9g}…{norm.max():.9g})")
    return q


def skew(v) -> np.ndarray:
    """``[v]x``: the (…, 3, 3) matrix with ``skew(a) @ b == cross(a, b)``."""
    v = np.asarray(v, dtype=np.float64)
    z = np.zeros(v.shape[:-1])
    return np.stack([
        np.stack([z, -v[..., 2], v[..., 1]], -1),
        np.stack([v[..., 2], z, -v[..., 0]], -1),
        np.stack([-v[..., 1], v[..., 0], z], -1),
    ], -2)


def quat_mul(a, b) -> np.ndarray:
    """Hamilton product ``a ⊗ b``."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    w1, x1, y1, z1 = np.moveaxis(a, -1, 0)
    w2, x2, y2, z2 = np.moveaxis(b, -1, 0)
    return np.stack([
        w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
        w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
        w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
        w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
    ], -1)


def quat_conj(q) -> np.ndarray:
    """Conjugate (the inverse of a unit quaternion)."""
    q = np.asarray(q, dtype=np.float64)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_exp(phi) -> np.ndarray:
    """``Exp(phi)``: unit quaternion of the rotation vector ``phi`` (rad)."""
    phi = np.asarray(phi, dtype=np.float64)
    angle = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * angle
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    s = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / safe)
    return np.concatenate([np.cos(half), s * phi], axis=-1)


def quat_log(q) -> np.ndarray:
    """``Log(q)``: rotation vector (rad, angle in [0, π]) of a unit quaternion."""
    q = np.asarray(q, dtype=np.float64)
    q = np.where(q[..., :1] < 0.0, -q, q)  # the short way round
    w, v = q[..., :1], q[..., 1:]
    vn = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(vn, w)
    small = vn < 1e-12
    scale = np.where(small, 2.0 / np.where(small, w, 1.0), angle / np.where(small, 1.0, vn))
    return scale * v


def quat_to_mat(q) -> np.ndarray:
    """``R(q)`` (…, 3, 3), body to navigation."""
    q = np.asarray(q, dtype=np.float64)
    if q.shape == (4,):  # one quaternion: Python floats (the same float64 products, without stacking 0-d arrays)
        w, x, y, z = (float(v) for v in q)
        return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def mat_to_quat(m) -> np.ndarray:
    """Unit quaternion (w ≥ 0) of a rotation matrix (…, 3, 3); robust branch per item (Shepperd)."""
    m = np.asarray(m, dtype=np.float64)
    flat = m.reshape(-1, 3, 3)
    out = np.empty((len(flat), 4))
    for k, r in enumerate(flat):
        tr = np.trace(r)
        i = int(np.argmax([tr, r[0, 0], r[1, 1], r[2, 2]]))
        if i == 0:
            s = 2.0 * np.sqrt(1.0 + tr)
            out[k] = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
        elif i == 1:
            s = 2.0 * np.sqrt(1.0 + 2 * r[0, 0] - tr)
            out[k] = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
        elif i == 2:
            s = 2.0 * np.sqrt(1.0 + 2 * r[1, 1] - tr)
            out[k] = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
        else:
            s = 2.0 * np.sqrt(1.0 + 2 * r[2, 2] - tr)
            out[k] = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    out[out[:, 0] < 0] *= -1.0
    out /= np.linalg.norm(out, axis=1, keepdims=True)
    return out.reshape((*m.shape[:-2], 4))


def euler_to_quat(roll, pitch, yaw) -> np.ndarray:
    """ZYX Euler angles (rad) -> quaternion of ``Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = (0.5 * np.asarray(a, dtype=np.float64) for a in (roll, pitch, yaw))
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.stack([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ], -1)


def quat_to_euler(q) -> np.ndarray:
    """Quaternion -> ZYX Euler angles (…, 3) = (roll, pitch, yaw) in rad; pitch in [-π/2, π/2]."""
    m = quat_to_mat(q)
    roll = np.arctan2(m[..., 2, 1], m[..., 2, 2])
    pitch = np.arcsin(np.clip(-m[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(m[..., 1, 0], m[..., 0, 0])
    return np.stack([roll, pitch, yaw], -1)


def euler_to_mat(roll, pitch, yaw) -> np.ndarray:
    """``Rz(yaw) Ry(pitch) Rx(roll)`` (…, 3, 3)."""
    return quat_to_mat(euler_to_quat(roll, pitch, yaw))
