"""Which part of a frame the device sends: the prior's projected object box, grown by its uncertainty.

Once the tracker holds a pose, it knows where the object is in the frame; a crop around it is a
fraction of the bytes (a 640x480 frame of the simulated room is ~88 kB as the device's JPEG; the
object's crop at 1.2 m ~10-20 kB), so it arrives sooner and decodes faster. The wire rule is in
`protos/flextrack/v1/pose_estimation.proto` (`Crop`): the image holds the rectangle, the intrinsics
stay the full frame's, the answer's pose is T_CO as ever.

The whole frame goes when there is nothing to crop to: before the first pose (`init`), right after
the object was lost or a pose was wrong (`failure`: the tracked pose may be off by more than its
covariance says), and when the grown box covers the frame or misses it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from client_sdk.refinement import RefinementRequest
from flextrack.v1 import pose_estimation_pb2 as pb


@dataclass(frozen=True)
class CropOptions:
    enabled: bool = True  # False: always the whole frame (the paper's)
    sigmas: float = 3.0  # each box side grown by this many standard deviations of the corners' projection
    margin_px: float = 24.0  # and by this many px: the background next to the outline that estimators read
    default_std_px: float = 10.0  # the projection's standard deviation for a prior without a covariance
    align_px: int = 16  # edges on multiples of this (JPEG's 16x16 blocks at most; the networks' strides)

    def __post_init__(self) -> None:
        if self.sigmas < 0 or self.margin_px < 0 or self.default_std_px < 0 or self.align_px < 1:
            raise ValueError("CropOptions: sigmas, margin_px and default_std_px must be >= 0, align_px >= 1")


def projection_std_px(camera, corners_O: np.ndarray, T_CO: np.ndarray, covariance: np.ndarray) -> np.ndarray | None:
    """(n, 2) standard deviations (u, v) in px of the corners' projections under a pose covariance (wire
    convention: rotation first, camera frame, left perturbation); None when a corner is behind the camera."""
    RX = corners_O @ T_CO[:3, :3].T
    X = RX + T_CO[:3, 3]
    z = X[:, 2]
    if np.any(z <= 1e-6):
        return None
    # d X / d e = [-[R X_O]x, I]; d uv / d X = [[fx/z, 0, -fx x/z^2], [0, fy/z, -fy y/z^2]]
    skew = np.zeros((len(X), 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -RX[:, 2], RX[:, 1], -RX[:, 0]
    skew -= skew.transpose(0, 2, 1)
    dX = np.concatenate([-skew, np.broadcast_to(np.eye(3), skew.shape)], axis=2)  # (n, 3, 6)
    dpi = np.zeros((len(X), 2, 3))
    dpi[:, 0, 0], dpi[:, 0, 2] = camera.fx / z, -camera.fx * X[:, 0] / z ** 2
    dpi[:, 1, 1], dpi[:, 1, 2] = camera.fy / z, -camera.fy * X[:, 1] / z ** 2
    J = dpi @ dX  # (n, 2, 6)
    var = np.einsum("nia,ab,nib->ni", J, np.asarray(covariance, dtype=float), J)
    return np.sqrt(np.maximum(var, 0.0))


def crop_rect(camera, corners_O: np.ndarray, T_CO: np.ndarray, covariance: np.ndarray | None,
              options: CropOptions = CropOptions()) -> tuple[int, int, int, int] | None:
    """(x, y, width, height) of the frame to send for a prior T_CO, or None for the whole frame: the
    object's box projected, grown by `sigmas` standard deviations and `margin_px`, aligned, clipped."""
    corners_O = np.asarray(corners_O, dtype=float)
    X = corners_O @ T_CO[:3, :3].T + T_CO[:3, 3]
    if np.any(X[:, 2] <= 1e-6):
        return None
    uv = np.stack([camera.fx * X[:, 0] / X[:, 2] + camera.cx, camera.fy * X[:, 1] / X[:, 2] + camera.cy], axis=1)
    if covariance is None:
        std = np.full(2, options.default_std_px)
    else:
        per_corner = projection_std_px(camera, corners_O, T_CO, covariance)
        if per_corner is None:
            return None
        std = per_corner.max(axis=0)
    grow = options.sigmas * std + options.margin_px
    lo, hi = uv.min(axis=0) - grow, uv.max(axis=0) + grow
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        return None
    a = options.align_px
    x0, y0 = max(0, int(lo[0] // a) * a), max(0, int(lo[1] // a) * a)
    x1, y1 = min(camera.width, -int(-hi[0] // a) * a), min(camera.height, -int(-hi[1] // a) * a)
    if x1 - x0 < a or y1 - y0 < a or (x1 - x0, y1 - y0) == (camera.width, camera.height):
        return None  # out of view (nothing to cut to) or the whole frame anyway
    return x0, y0, x1 - x0, y1 - y0


def request_crop(tracker, request: RefinementRequest, corners_O: np.ndarray,
                 options: CropOptions = CropOptions()) -> pb.Crop | None:
    """The `Crop` for the frame of a request the tracker issued, or None for the whole frame: a regular
    refinement of a tracked pose is cropped to its prior; a first request or one after a failure is not."""
    if not options.enabled or request.reason != "refine":
        return None
    T_CO = tracker.pose_at(request.frame_t_ns)
    if T_CO is None:
        return None
    covariance_at = getattr(tracker, "pose_covariance_at", None)
    cov = covariance_at(request.frame_t_ns) if covariance_at is not None else None
    rect = crop_rect(tracker.camera, corners_O, T_CO, cov, options)
    return None if rect is None else pb.Crop(x=rect[0], y=rect[1], width=rect[2], height=rect[3])
