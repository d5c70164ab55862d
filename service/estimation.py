"""EstimationService: a wire request in, a wire response (or a typed error) out; no gRPC server needed.

`estimate` raises the estimators' typed errors (the servicer maps them to gRPC codes for unary
calls); `answer` never raises and puts them in the response status instead (the Track stream).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from estimators.base import EstimateInput, EstimatorError, InvalidInput, Status, UnknownEstimator
from estimators.registry import EstimatorRegistry
from flextrack import wire
from flextrack.v1 import pose_estimation_pb2 as pb
from service import request_decoding
from service.limits import RequestLimits, clip_message, echo

log = logging.getLogger("flextrack.service")
MAX_CHECKED_CONSTANTS = 16

PB_STATUS = {
    Status.OK: pb.EstimateResponse.OK,
    Status.OBJECT_NOT_FOUND: pb.EstimateResponse.OBJECT_NOT_FOUND,
    Status.INVALID_INPUT: pb.EstimateResponse.INVALID_INPUT,
    Status.INTERNAL: pb.EstimateResponse.INTERNAL,
}
INTERNAL_MESSAGE = "internal error in the estimator (details are in the server log)"


class EstimationService:
    def __init__(self, registry: EstimatorRegistry, limits: RequestLimits | None = None):
        self.registry = registry
        self.limits = limits or RequestLimits()  # string lengths, keypoints, image pixels (service.limits)
        self._checked_constants: list[np.ndarray] = []  # read-only covariances already found valid

    def _wire_covariance(self, cov) -> pb.PoseCovariance:
        """The estimator's covariance for the wire, checked: the wire promises a symmetric positive
        definite 6x6 (BadCovariance otherwise). A read-only array checked once (the oracle's constant
        ones) is not checked again: the check costs ~12 us, a few % of a cheap frame's server CPU."""
        constant = isinstance(cov, np.ndarray) and not cov.flags.writeable
        if not (constant and any(c is cov for c in self._checked_constants)):
            wire.check_covariance(cov, "the estimator's covariance")
            if constant and len(self._checked_constants) < MAX_CHECKED_CONSTANTS:
                self._checked_constants.append(cov)
        return wire.covariance_to_pb(cov)

    def list_estimators(self) -> pb.ListEstimatorsResponse:
        return pb.ListEstimatorsResponse(estimators=[
            pb.EstimatorInfo(name=e.name, kind=e.kind, version=e.version, objects=e.objects, ready=e.ready,
                             is_default=e.name == self.registry.default, description=e.description)
            for e in self.registry])

    def is_cheap(self, request: pb.EstimateRequest) -> bool:
        """Whether the request's estimator is cheap enough to call on the event loop."""
        try:
            return self.registry.get(request.estimator).cheap
        except UnknownEstimator:
            return True  # answered at once with an error

    def estimate(self, request: pb.EstimateRequest) -> pb.EstimateResponse:
        start = time.perf_counter()
        self.limits.check(request)  # before anything reads the strings or the image
        estimator = self.registry.get(request.estimator)
        camera = request_decoding.decode_camera(request.intrinsics)
        keypoints = request_decoding.decode_keypoints(request.keypoints)
        camera, keypoints = request_decoding.decode_crop(request, camera, keypoints)  # a crop: its own camera
        prior_T_CO, prior_covariance = request_decoding.decode_prior(request)
        if estimator.uses_image:
            image = request_decoding.decode_image(request.image, camera)
            if image is None:
                raise InvalidInput(f"estimator '{estimator.name}' needs an image")
        else:
            request_decoding.check_image(request.image, camera)
            image = None
        decoded = time.perf_counter()
        out = estimator.estimate(EstimateInput(
            frame_id=request.frame_id, capture_time_ns=request.capture_time_ns, object_id=request.object_id,
            sequence=request.sequence, session_id=request.session_id, camera=camera, image=image, keypoints=keypoints,
            prior_T_CO=prior_T_CO, prior_covariance=prior_covariance))
        done = time.perf_counter()
        pose = wire.pose_to_pb(out.T_CO) if out.T_CO is not None else None
        covariance, message = None, out.message
        if out.T_CO is not None and out.covariance is not None:
            try:  # a bad one is withheld, never sent
                covariance = self._wire_covariance(out.covariance)
            except wire.BadCovariance as exc:
                log.warning("covariance withheld", extra={"estimator": estimator.name, "reason": str(exc)})
                message = clip_message(f"{message}; covariance withheld: {exc}" if message else f"covariance withheld: {exc}")
        # Stage timings only for estimators that report stages: filling the map costs more than the
        # oracle's whole estimate, and server_time_ms already covers a single-stage one.
        stage_ms = {"decode": (decoded - start) * 1e3, "estimate": (done - decoded) * 1e3, **out.stage_ms} \
            if out.stage_ms else None
        return pb.EstimateResponse(
            frame_id=request.frame_id, capture_time_ns=request.capture_time_ns, status=PB_STATUS[out.status],
            message=message, pose=pose, pose_covariance=covariance, confidence=out.confidence,
            estimator=f"{estimator.name}@{estimator.version}", server_time_ms=(done - start) * 1e3, stage_ms=stage_ms)

    def answer(self, request: pb.EstimateRequest) -> pb.EstimateResponse:
        """Like `estimate`, but every failure becomes the response's status and message."""
        try:
            return self.estimate(request)
        except EstimatorError as exc:  # unknown estimator/object/sequence or bad input: the client's to fix
            status, message = pb.EstimateResponse.INVALID_INPUT, clip_message(str(exc))
        except Exception:
            log.exception("estimator failed", extra={"frame_id": request.frame_id, "estimator": echo(request.estimator)})
            status, message = pb.EstimateResponse.INTERNAL, INTERNAL_MESSAGE
        return pb.EstimateResponse(frame_id=request.frame_id, capture_time_ns=request.capture_time_ns,
                                   status=status, message=message)
