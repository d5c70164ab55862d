"""PIM: the paper's Pose Inspection Algorithm (Algorithm 1) on the object's 3D bounding box.

TRACKING_LOST when the object's bounding box in the image covers less than frame area / 100
(THR_area) or any corner of its 3D box is not in front of the camera (a projection through the
camera plane is meaningless); WRONG_POSE when the mean offset of the 8 projected corners from the
previous frame is >= THR_2d = 10 + 10 * 30 / fps px; FINE otherwise.

The area is that of the image bounding box: the axis-aligned rectangle around the 8 projected
corners of the object's 3D box. The paper's Section 3.5 says "first find the bounding box of the
object in the image based on the pose. We check the projection area"; Algorithm 1's "area
surrounded by pBox2DsNow" is read the same way. (The silhouette polygon of the projected 3D box is
smaller, by 10-40 % for a box seen at an angle, and would call a 15 cm object at 1.2 m lost.)
"""

from __future__ import annotations

import enum

import numpy as np

from flextrack.geometry.camera import PinholeCamera


class Status(enum.Enum):
    """What a frame's pose is worth (the PIA's verdict; the filter adds its own uncertainty check).

    INITIALIZING: no pose yet (waiting for IMU or the first backend answer). FINE: show it.
    WRONG_POSE: it moved further than the frame rate allows since the last frame. TRACKING_LOST: the
    object is out of view or too small, no backend answer came for too long, or (filter) the pose's
    projected uncertainty is too large. A frame that is not FINE asks the backend again."""

    INITIALIZING = "initializing"
    FINE = "fine"
    WRONG_POSE = "wrong_pose"
    TRACKING_LOST = "tracking_lost"


# Corner i of a box is lo + bit2(i) * ex + bit1(i) * ey + bit0(i) * ez, the order of
# flextrack.geometry.camera.bbox_corners.
_BITS = np.array([[(i >> 2) & 1, (i >> 1) & 1, i & 1] for i in range(8)], dtype=float)


def check_box(corners_O: np.ndarray) -> np.ndarray:
    """The (8, 3) corners as float, or ValueError unless they form a box in `bbox_corners` order."""
    P = np.asarray(corners_O, dtype=float)
    if P.shape != (8, 3) or not np.all(np.isfinite(P)):
        raise ValueError(f"bbox_corners_O must be a finite (8, 3) array, got shape {P.shape}")
    edges = np.stack([P[4] - P[0], P[2] - P[0], P[1] - P[0]])
    size = float(np.abs(edges).max())
    if size <= 0 or not np.allclose(P, P[0] + _BITS @ edges, atol=1e-9 + 1e-6 * size):
        raise ValueError("bbox_corners_O must be the 8 corners of a box in the order of "
                         "flextrack.geometry.camera.bbox_corners (index = 4*ix + 2*iy + iz)")
    return P


class PoseInspector:
    """Algorithm 1 for one object and one camera; thresholds precomputed, no allocation beyond numpy's."""

    def __init__(self, camera: PinholeCamera, corners_O: np.ndarray, area_divisor: float = 100.0,
                 px_error: float = 10.0, px_motion: float = 10.0, base_rate: float = 30.0,
                 near_m: float = 1e-3) -> None:
        self.corners_O = check_box(corners_O)
        self._corners_h = np.hstack([self.corners_O, np.ones((8, 1))])  # homogeneous, (8, 4)
        self._K = camera.K
        self.thr_area = camera.width * camera.height / area_divisor
        self._px_error, self._px_motion, self._base_rate = px_error, px_motion, base_rate
        self._near = near_m

    def thr_2d(self, fps: float) -> float:
        return self._px_error + self._px_motion * self._base_rate / fps

    def project(self, T_CO: np.ndarray) -> np.ndarray | None:
        """(8, 2) pixels of the corners seen with the 4x4 pose T_CO, or None when a corner is not in
        front of the camera. Two small matrix products: this runs on every frame."""
        X = self._corners_h @ (self._K @ T_CO[:3]).T  # rows (z u, z v, z)
        z = X[:, 2:3]
        if z.min() < self._near:
            return None
        return X[:, :2] / z

    @staticmethod
    def area(uv: np.ndarray) -> float:
        """Area in px^2 of the image bounding box of the projected corners (see module doc)."""
        u, v = uv[:, 0].tolist(), uv[:, 1].tolist()  # plain floats: ~2x faster than numpy's min/max here
        return (max(u) - min(u)) * (max(v) - min(v))

    def inspect(self, uv: np.ndarray | None, uv_last: np.ndarray | None, fps: float | None) -> tuple[Status, str]:
        """Algorithm 1: the status and a human reason, from this frame's and the last frame's corners."""
        if uv is None:
            return Status.TRACKING_LOST, "tracking lost: the box is not in front of the camera"
        area = self.area(uv)
        if area < self.thr_area:
            return Status.TRACKING_LOST, f"tracking lost: box area {area:.0f} px^2 < {self.thr_area:.0f} px^2"
        if uv_last is not None and fps is not None:
            d = uv - uv_last
            offset = float(np.sqrt((d * d).sum(axis=1)).mean())
            thr = self.thr_2d(fps)
            if offset >= thr:
                return Status.WRONG_POSE, f"wrong pose: corner offset {offset:.1f} px >= {thr:.1f} px"
        return Status.FINE, "tracking"
