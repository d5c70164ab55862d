"""The one home of the conversions between numpy poses/covariances and their wire messages.

numpy and the generated protobuf code only: the client SDK, the service and the runners all use it.
The covariance convention is written in `protos/flextrack/v1/pose_estimation.proto` (PoseCovariance):
error (d_theta, d_t), rotation first, both in the camera frame, R_true = Exp(d_theta) R_est,
t_true = t_est + d_t.
"""

from __future__ import annotations

from math import isfinite

import numpy as np

from flextrack.geometry import se3, so3
from flextrack.v1 import pose_estimation_pb2 as pb

MAX_STD_RAD = np.pi  # a rotation standard deviation above this says nothing: refused as nonsense
MAX_STD_M = 1e3


class BadCovariance(ValueError):
    """A covariance that is not a finite, symmetric positive-definite 6x6 matrix (the message says why)."""


def pose_to_pb(T: np.ndarray) -> pb.Pose:
    q, t = se3.to_quat_translation(np.asarray(T, dtype=float))
    return pb.Pose(tx=t[0], ty=t[1], tz=t[2], qw=q[0], qx=q[1], qy=q[2], qz=q[3])


def pose_from_pb(pose: pb.Pose) -> np.ndarray:
    """T (4x4) from a wire pose; the quaternion is normalised (ValueError when it is zero or not finite)."""
    q = np.array([pose.qw, pose.qx, pose.qy, pose.qz], dtype=float)
    t = np.array([pose.tx, pose.ty, pose.tz], dtype=float)
    n = float(np.linalg.norm(q))
    if not (np.isfinite(n) and n > 1e-9 and np.all(np.isfinite(t))):
        raise ValueError("pose must have a finite translation and a non-zero finite quaternion")
    return se3.from_quat_translation(q / n, t)


def check_covariance(cov, name: str = "covariance") -> np.ndarray:
    """The 6x6 covariance as a float array; BadCovariance unless finite, symmetric and positive definite.
    The element checks run on Python floats: this is on every backend answer's path in the tracker,
    where a dozen numpy reductions on a 6x6 cost tens of microseconds."""
    try:
        c = np.asarray(cov, dtype=float)
    except (TypeError, ValueError):
        raise BadCovariance(f"{name} must be numbers") from None
    if c.size != 36:
        raise BadCovariance(f"{name} must have 36 values (6x6 row-major), got {c.size}")
    m = c.ravel().tolist()
    if not all(map(isfinite, m)):
        raise BadCovariance(f"{name} must be finite")
    scale = max(max(map(abs, m)), 1e-300)
    if max(abs(m[6 * i + j] - m[6 * j + i]) for i in range(6) for j in range(i + 1, 6)) > 1e-9 * scale:
        raise BadCovariance(f"{name} must be symmetric")
    c = c.reshape(6, 6)
    c = 0.5 * (c + c.T)
    try:
        np.linalg.cholesky(c)
    except np.linalg.LinAlgError:
        raise BadCovariance(f"{name} must be positive definite") from None
    if max(m[0], m[7], m[14]) > MAX_STD_RAD ** 2 or max(m[21], m[28], m[35]) > MAX_STD_M ** 2:
        raise BadCovariance(f"{name} is too large to mean anything (std above {MAX_STD_RAD:.2f} rad or {MAX_STD_M:g} m)")
    return c


def intrinsics_to_pb(camera) -> pb.Intrinsics:
    """The wire intrinsics of a PinholeCamera (fx, fy, cx, cy, width, height and its distortion, never dropped)."""
    return pb.Intrinsics(fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy, width=camera.width,
                         height=camera.height, distortion=list(camera.distortion))


def covariance_to_pb(cov: np.ndarray | None) -> pb.PoseCovariance | None:
    return None if cov is None else pb.PoseCovariance(data=np.asarray(cov, dtype=float).ravel().tolist())


def covariance_from_pb(msg: pb.PoseCovariance, name: str = "covariance") -> np.ndarray | None:
    """None for an empty message (the sender gave none); BadCovariance for a bad one."""
    if not len(msg.data):
        return None
    return check_covariance(list(msg.data), name)


def diagonal_covariance(std_rot_rad: float, std_trans_m: float) -> np.ndarray:
    """Isotropic per-axis standard deviations as a 6x6 covariance in the wire convention."""
    return np.diag([std_rot_rad ** 2] * 3 + [std_trans_m ** 2] * 3)


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> np.ndarray:
    """The error e = (d_theta, d_t) of T_est in the wire convention: R_true = Exp(d_theta) R_est,
    t_true = t_est + d_t (camera frame, rad then m); e^T inv(covariance) e is the NEES."""
    d_theta = so3.log(T_true[:3, :3] @ T_est[:3, :3].T)
    return np.concatenate([d_theta, T_true[:3, 3] - T_est[:3, 3]])
