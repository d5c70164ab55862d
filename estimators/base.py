"""What every estimator takes, returns and raises, independent of gRPC.

The service turns a wire request into an `EstimateInput`, calls `Estimator.estimate`, and maps the
typed exceptions below to gRPC codes (unary) or response statuses (Track stream).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from flextrack.geometry.camera import PinholeCamera


class Status(enum.Enum):
    OK = "OK"
    OBJECT_NOT_FOUND = "OBJECT_NOT_FOUND"
    INVALID_INPUT = "INVALID_INPUT"
    INTERNAL = "INTERNAL"


class EstimatorError(Exception):
    """A request the estimator cannot answer; the message tells the client what to fix."""


class InvalidInput(EstimatorError):
    """Malformed or insufficient input (gRPC INVALID_ARGUMENT)."""


class UnknownObject(EstimatorError):
    """The object id is not one the estimator knows (gRPC NOT_FOUND)."""


class UnknownEstimator(EstimatorError):
    """No estimator of that name is registered (gRPC NOT_FOUND)."""


class UnknownSequence(EstimatorError):
    """An oracle was asked for a sequence it has not loaded (gRPC FAILED_PRECONDITION)."""


@dataclass(frozen=True)
class EstimateInput:
    frame_id: int
    capture_time_ns: int
    object_id: str = ""  # empty: the estimator's only object
    sequence: str = ""  # for oracles; empty: the only loaded sequence
    session_id: str = ""  # the device session, for estimators that keep per-session state; empty: none
    camera: PinholeCamera | None = None  # None when the request carried no intrinsics
    image: np.ndarray | None = None  # HxWx3 uint8 RGB or HxW gray; None unless the estimator uses images
    keypoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (N, 3) rows: id, u, v (px)
    prior_T_CO: np.ndarray | None = None  # the device's predicted T_CO at the capture time, when it sent one
    prior_covariance: np.ndarray | None = None  # its 6x6 covariance (flextrack.wire convention); None: not sent


@dataclass
class EstimateOutput:
    status: Status
    T_CO: np.ndarray | None = None  # 4x4, metres, at the input's capture time
    confidence: float = 0.0  # 0..1
    covariance: np.ndarray | None = None  # 6x6 of T_CO in the flextrack.wire convention; set with every pose
    message: str = ""
    stage_ms: dict[str, float] = field(default_factory=dict)

    @classmethod
    def not_found(cls, message: str) -> EstimateOutput:
        return cls(Status.OBJECT_NOT_FOUND, message=message)


class Estimator:
    """Base class: subclasses set `kind`, `version`, and implement `estimate`.

    `uses_image` tells the service whether to decode the request's image (decoding a 100 kB JPEG
    costs milliseconds, wasted on estimators that never look at pixels). `cheap` marks estimators
    that answer in well under a millisecond: the service calls them on its event loop, where a hop
    to a worker thread would cost more than the call itself. `needs_prior` marks estimators that only
    refine the device's prior (they cannot give a first pose; a `chained` one can).
    """

    kind: str = ""
    version: str = "0"
    uses_image: bool = False
    cheap: bool = False
    needs_prior: bool = False
    description: str = ""

    def __init__(self, name: str, object_ids: list[str] | tuple[str, ...] = ()):
        self.name = name
        self._object_ids = list(object_ids)

    @property
    def objects(self) -> list[str]:
        return list(self._object_ids)

    @property
    def ready(self) -> bool:
        return True

    def resolve_object(self, object_id: str) -> str:
        """The object a request means: its id, or the only known object when it is empty."""
        known = self.objects
        if not object_id:
            if len(known) == 1:
                return known[0]
            raise InvalidInput(f"estimator '{self.name}' knows objects {known}: set object_id")
        if object_id not in known:
            raise UnknownObject(f"estimator '{self.name}' does not know object '{object_id}'; known: {known}")
        return object_id

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        raise NotImplementedError

    def estimate_batch(self, inputs: list[EstimateInput]) -> list[EstimateOutput]:
        """Several frames at once; estimators that can batch (networks) override this."""
        return [self.estimate(inp) for inp in inputs]
