"""Rigid-body kinematics at arrays of times, exact: pose, velocity, acceleration, body rates.

Orientations are products of elementary rotations (a fixed axis, an angle jet) and constant
matrices; the body-frame angular velocity and acceleration of a product follow from
  R = R_A R_B:  w = R_B^T w_A + w_B,   alpha = R_B^T alpha_A - w_B x (R_B^T w_A) + alpha_B.
A frame rigidly attached to a moving one (the IMU beside the camera) gets its own velocity and
acceleration from the lever-arm terms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flextrack.geometry import so3
from flextrack.simulator.jet import Jet

GRAVITY_W = np.array([0.0, 0.0, -9.81])  # world z is up


@dataclass
class Kinematics:
    """State of a frame X in the world at N times."""

    R_WX: np.ndarray  # (N, 3, 3)
    p_WX: np.ndarray  # (N, 3)
    v_WX: np.ndarray  # (N, 3) world velocity
    a_WX: np.ndarray  # (N, 3) world acceleration (gravity not included)
    w_X: np.ndarray  # (N, 3) angular velocity in X
    alpha_X: np.ndarray  # (N, 3) angular acceleration in X

    def attached(self, T_XY: np.ndarray) -> Kinematics:
        """The kinematics of frame Y rigidly attached to X with pose T_XY."""
        R_XY, p_XY = T_XY[:3, :3], T_XY[:3, 3]
        w, al = self.w_X, self.alpha_X
        lever_v = np.cross(w, p_XY)
        lever_a = np.cross(al, p_XY) + np.cross(w, lever_v)
        rot = lambda vecs: np.einsum("nij,nj->ni", self.R_WX, vecs)
        return Kinematics(
            self.R_WX @ R_XY,
            self.p_WX + self.R_WX @ p_XY,
            self.v_WX + rot(lever_v),
            self.a_WX + rot(lever_a),
            w @ R_XY,
            al @ R_XY,
        )

    def specific_force(self, gravity_W: np.ndarray = GRAVITY_W) -> np.ndarray:
        """What an accelerometer at X reads: R_WX^T (a - g), (N, 3)."""
        return np.einsum("nji,nj->ni", self.R_WX, self.a_WX - gravity_W)

    def poses(self) -> np.ndarray:
        T = np.tile(np.eye(4), (len(self.p_WX), 1, 1))
        T[:, :3, :3] = self.R_WX
        T[:, :3, 3] = self.p_WX
        return T


def axis_rotation(axis: np.ndarray, angle: Jet) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, w, alpha) of a rotation by `angle` about a fixed unit axis (Rodrigues, vectorised)."""
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    R = so3.exp_many(np.asarray(angle.v, float)[:, None] * u)
    return R, angle.d1[:, None] * u, angle.d2[:, None] * u


def compose_rotations(factors: list, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Product of factors left to right; each is a constant 3x3 or an (axis, angle Jet) pair."""
    R = np.tile(np.eye(3), (n, 1, 1))
    w = np.zeros((n, 3))
    alpha = np.zeros((n, 3))
    for factor in factors:
        if isinstance(factor, np.ndarray):
            RB, wB, aB = np.broadcast_to(factor, (n, 3, 3)), np.zeros((n, 3)), np.zeros((n, 3))
        else:
            RB, wB, aB = axis_rotation(*factor)
        w_in_B = np.einsum("nji,nj->ni", RB, w)  # R_B^T w_A
        alpha = np.einsum("nji,nj->ni", RB, alpha) - np.cross(wB, w_in_B) + aB
        w = w_in_B + wB
        R = R @ RB
    return R, w, alpha
