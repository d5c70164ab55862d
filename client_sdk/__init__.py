"""flextrack's device side: the tracker core and, around it, the transport to the backend.

The core is a deterministic state machine: PPM (IMU propagation), PIM (the Pose Inspection
Algorithm) and a refinement from backend poses, either an error-state Kalman filter
(`FilterTracker`, the default) or the paper's PRM with its Bias Self-Correction Mechanism
(`Tracker`); `create_tracker` picks by `TrackerOptions.fusion`. It imports numpy, grpcio and
protobuf at most. See docs/tracker.md.
"""

from client_sdk.eskf.options import FilterOptions
from client_sdk.eskf.tracker import FilterTracker
from client_sdk.inspection import Status
from client_sdk.options import TrackerOptions
from client_sdk.refinement import RefinementRequest, ResponseOutcome
from client_sdk.state import TrackerState
from client_sdk.tracker import FrameResult, Tracker


def create_tracker(options: TrackerOptions | None, camera, T_BC, bbox_corners_O) -> Tracker | FilterTracker:
    """The tracker core `options.fusion` names (default: the error-state filter).

    camera: a `flextrack.geometry.camera.PinholeCamera` (px). T_BC: 4x4, maps camera-frame points into
    the IMU body frame (metres). bbox_corners_O: (8, 3) corners of the object's box in its own frame
    (metres), in `flextrack.geometry.camera.bbox_corners` order (corner i = lo + bit2(i) ex + bit1(i) ey
    + bit0(i) ez); the PIA projects them. Invalid arguments raise ValueError."""
    options = options if options is not None else TrackerOptions()
    cls = FilterTracker if options.fusion == "filter" else Tracker
    return cls(options, camera, T_BC, bbox_corners_O)


__all__ = [
    "FilterOptions",
    "FilterTracker",
    "FrameResult",
    "RefinementRequest",
    "ResponseOutcome",
    "Status",
    "Tracker",
    "TrackerOptions",
    "TrackerState",
    "create_tracker",
]
