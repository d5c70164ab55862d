"""flextrack's device side: the tracker core and, around it, the transport to the backend.

The core (`Tracker`) is the paper's frontend as a deterministic state machine: PPM (IMU
propagation), PIM (the Pose Inspection Algorithm) and PRM (backend refinement with the Bias
Self-Correction Mechanism). It imports numpy, grpcio and protobuf at most. See docs/tracker.md.
"""

from client_sdk.inspection import Status
from client_sdk.options import TrackerOptions
from client_sdk.refinement import RefinementRequest, ResponseOutcome
from client_sdk.state import TrackerState
from client_sdk.tracker import FrameResult, Tracker

__all__ = ["FrameResult", "RefinementRequest", "ResponseOutcome", "Status", "Tracker", "TrackerOptions",
           "TrackerState"]
