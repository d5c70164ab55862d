"""Rigid transforms as 4x4 matrices. `T_AB` maps points from frame B into frame A."""

from __future__ import annotations

import numpy as np

from flextrack.geometry import so3


def make(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def inverse(T: np.ndarray) -> np.ndarray:
    R = T[:3, :3]
    return make(R.T, -R.T @ T[:3, 3])


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply T to an (N, 3) array of points."""
    return points @ T[:3, :3].T + T[:3, 3]


def from_quat_translation(q_wxyz: np.ndarray, t: np.ndarray) -> np.ndarray:
    return make(so3.matrix_from_quat(q_wxyz), np.asarray(t, dtype=float))


def to_quat_translation(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(q_wxyz, t) of T."""
    return so3.quat_from_matrix(T[:3, :3]), T[:3, 3].copy()


def interpolate(T0: np.ndarray, T1: np.ndarray, s: float) -> np.ndarray:
    """Pose between T0 (s=0) and T1 (s=1): linear in translation, slerp in rotation."""
    q = so3.slerp(so3.quat_from_matrix(T0[:3, :3]), so3.quat_from_matrix(T1[:3, :3]), s)
    return make(so3.matrix_from_quat(q), (1 - s) * T0[:3, 3] + s * T1[:3, 3])


def interpolate_at(times_ns: np.ndarray, poses: np.ndarray, t_ns: int) -> np.ndarray | None:
    """Pose at t_ns from sorted sample times and (N, 4, 4) poses; None outside their span."""
    if len(times_ns) == 0 or t_ns < times_ns[0] or t_ns > times_ns[-1]:
        return None
    i = int(np.searchsorted(times_ns, t_ns, side="right")) - 1
    if i >= len(times_ns) - 1 or times_ns[i] == t_ns:
        return poses[i].copy()
    s = (t_ns - times_ns[i]) / (times_ns[i + 1] - times_ns[i])
    return interpolate(poses[i], poses[i + 1], float(s))


def turned_about_line_of_sight(T_CO: np.ndarray, center_O: np.ndarray, angle: float = np.pi) -> np.ndarray:
    """T_CO with the object turned by `angle` about the camera's ray through its point `center_O`: the object
    stays where it is in the image, turned in it (180 deg: the pose a tracker that lost its orientation holds)."""
    c = T_CO[:3, :3] @ center_O + T_CO[:3, 3]
    R_turn = so3.exp(angle * c / max(float(np.linalg.norm(c)), 1e-12))
    return make(R_turn @ T_CO[:3, :3], R_turn @ (T_CO[:3, 3] - c) + c)
