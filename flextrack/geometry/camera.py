"""Pinhole camera (OpenCV convention: x right, y down, z forward) and projection."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from flextrack.geometry import se3

# LineMOD's intrinsics (BOP lm/lmo camera.json), the default for simulated 640x480 frames.
LINEMOD_FX, LINEMOD_FY, LINEMOD_CX, LINEMOD_CY = 572.4114, 573.57043, 325.2611, 242.04899


@dataclass(frozen=True)
class PinholeCamera:
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    distortion: tuple[float, ...] = field(default=())

    @classmethod
    def linemod(cls) -> PinholeCamera:
        return cls(LINEMOD_FX, LINEMOD_FY, LINEMOD_CX, LINEMOD_CY, 640, 480)

    @classmethod
    def from_K(cls, K: np.ndarray, width: int, height: int, distortion=()) -> PinholeCamera:
        K = np.asarray(K, dtype=float).reshape(3, 3)
        return cls(K[0, 0], K[1, 1], K[0, 2], K[1, 2], int(width), int(height), tuple(distortion))

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def project(self, points_C: np.ndarray) -> np.ndarray:
        """(N, 2) pixel coordinates of (N, 3) camera-frame points (no distortion)."""
        z = points_C[:, 2]
        return np.stack(
            [self.fx * points_C[:, 0] / z + self.cx, self.fy * points_C[:, 1] / z + self.cy], axis=1
        )


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """R_CW of an OpenCV camera (x right, y down, z forward) at `eye` looking at `target`, with `up` (a
    world direction not along the view) pointing up in the image: rows are the camera's axes in W."""
    z = np.asarray(target, dtype=float) - np.asarray(eye, dtype=float)
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=float))
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def project_model(camera: PinholeCamera, T_CO: np.ndarray, points_O: np.ndarray) -> np.ndarray:
    """Pixels of object-frame points seen with pose T_CO."""
    return camera.project(se3.transform_points(T_CO, points_O))


def bbox_corners(points: np.ndarray) -> np.ndarray:
    """The 8 corners of the axis-aligned bounding box of (N, 3) points."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
