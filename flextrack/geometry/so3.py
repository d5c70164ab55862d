"""Rotations: Rodrigues exp/log, quaternions (always w, x, y, z order here) and slerp."""

from __future__ import annotations

import math

import numpy as np

_SMALL_ANGLE = 1e-8


def skew(v: np.ndarray) -> np.ndarray:
    """3x3 matrix [v]x such that skew(v) @ u == cross(v, u)."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def skew_batch(v: np.ndarray) -> np.ndarray:
    """(N, 3, 3) matrices [v_i]x of (N, 3) vectors."""
    v = np.asarray(v, dtype=float)
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


def exp(phi: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector phi (Rodrigues' formula, the paper's Eq. 2)."""
    phi = np.asarray(phi, dtype=float)
    angle = float(np.linalg.norm(phi))
    B = skew(phi)
    if angle < _SMALL_ANGLE:
        return np.eye(3) + B + 0.5 * B @ B
    return (
        np.eye(3)
        + (np.sin(angle) / angle) * B
        + ((1.0 - np.cos(angle)) / angle**2) * (B @ B)
    )


def exp_many(phi: np.ndarray) -> np.ndarray:
    """`exp` of (N, 3) rotation vectors at once, (N, 3, 3): the same Rodrigues formula, vectorised (the
    simulator's integrator and motion programs)."""
    phi = np.asarray(phi, dtype=float)
    angle = np.linalg.norm(phi, axis=1)
    small = angle < 1e-8
    safe = np.where(small, 1.0, angle)
    a = np.where(small, 1.0 - angle**2 / 6, np.sin(safe) / safe)[:, None, None]
    b = np.where(small, 0.5 - angle**2 / 24, (1 - np.cos(safe)) / safe**2)[:, None, None]
    K = skew_batch(phi)
    return np.eye(3) + a * K + b * (K @ K)


def log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of R (inverse of `exp`), robust near 0 and pi."""
    return rotvec_from_quat(quat_from_matrix(R))


def angle_deg(R: np.ndarray) -> float:
    """Rotation angle of R in degrees (BOP's `re` when R = R_est @ R_gt.T)."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) with w >= 0 of the rotation matrix R (Shepperd's method).

    Scalar maths on Python floats: this runs once per served frame, where numpy's per-element
    overhead would cost several times more.
    """
    (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = np.asarray(R, dtype=float)[:3, :3].tolist()
    tr = r00 + r11 + r22
    candidates = (tr, r00, r11, r22)
    i = candidates.index(max(candidates))
    if i == 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = (0.25 * s, (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s)
    elif i == 1:
        s = 2.0 * math.sqrt(1.0 + r00 - r11 - r22)
        q = ((r21 - r12) / s, 0.25 * s, (r01 + r10) / s, (r02 + r20) / s)
    elif i == 2:
        s = 2.0 * math.sqrt(1.0 - r00 + r11 - r22)
        q = ((r02 - r20) / s, (r01 + r10) / s, 0.25 * s, (r12 + r21) / s)
    else:
        s = 2.0 * math.sqrt(1.0 - r00 - r11 + r22)
        q = ((r10 - r01) / s, (r02 + r20) / s, (r12 + r21) / s, 0.25 * s)
    norm = math.sqrt(sum(c * c for c in q))
    sign = 1.0 if q[0] >= 0 else -1.0
    return np.array([sign * c / norm for c in q])


def matrix_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of the quaternion q = (w, x, y, z); q need not be normalised."""
    w, x, y, z = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotvec_from_quat(q: np.ndarray) -> np.ndarray:
    """Rotation vector of the unit quaternion q = (w, x, y, z)."""
    q = np.asarray(q, dtype=float)
    q = q if q[0] >= 0 else -q
    v = q[1:]
    s = float(np.linalg.norm(v))
    if s < _SMALL_ANGLE:
        return 2.0 * v / max(q[0], _SMALL_ANGLE)
    return 2.0 * np.arctan2(s, q[0]) * v / s


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Spherical interpolation from q0 (s=0) to q1 (s=1), shortest path, (w, x, y, z)."""
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(d)
    return (np.sin((1 - s) * theta) * q0 + np.sin(s * theta) * q1) / np.sin(theta)
