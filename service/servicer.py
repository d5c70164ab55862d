"""The PoseEstimation servicer: a thin grpc.aio layer over EstimationService.

Estimator calls run in a thread pool so that the event loop keeps serving other streams while
one frame is being estimated; only estimators marked `cheap` are called on the loop itself.
"""

from __future__ import annotations

import asyncio
import logging
from concurrent.futures import Executor

import grpc

from estimators.base import EstimatorError, InvalidInput, UnknownEstimator, UnknownObject, UnknownSequence
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.estimation import INTERNAL_MESSAGE, EstimationService
from service.limits import clip_message, echo

log = logging.getLogger("flextrack.service")

GRPC_CODES = {
    InvalidInput: grpc.StatusCode.INVALID_ARGUMENT,
    UnknownEstimator: grpc.StatusCode.NOT_FOUND,
    UnknownObject: grpc.StatusCode.NOT_FOUND,
    UnknownSequence: grpc.StatusCode.FAILED_PRECONDITION,
}
LOADING_MESSAGE = "the estimators are still loading; retry shortly"


class PoseEstimationServicer(pb_grpc.PoseEstimationServicer):
    def __init__(self, executor: Executor, service: EstimationService | None = None):
        self.executor = executor
        self.service = service  # None until the estimators have loaded
        self.running_after_cancel = 0  # cancelled calls whose estimator thread still works on their frame

    async def _run(self, fn, request):
        if self.service.is_cheap(request):
            return fn(request)
        work = asyncio.get_running_loop().run_in_executor(self.executor, fn, request)
        try:
            return await asyncio.shield(work)
        except asyncio.CancelledError:
            # The call is gone (the client cancelled it, or its deadline passed), but a thread cannot be stopped:
            # hold the call until its work really ends, so that the admission bound, which frees the call's slot
            # when the call ends, keeps counting the thread that still runs, then end it as cancelled.
            self.running_after_cancel += 1
            try:
                while not work.done():
                    try:
                        await asyncio.shield(work)
                    except asyncio.CancelledError:
                        continue  # cancelled again (server shutdown): the work still holds its thread
                    except Exception:  # noqa: BLE001 - the answer nobody waits for any more
                        break
                if not work.cancelled():
                    work.exception()  # retrieved: asyncio would log an unretrieved one
            finally:
                self.running_after_cancel -= 1
            raise

    async def Estimate(self, request, context):
        if self.service is None:
            await context.abort(grpc.StatusCode.UNAVAILABLE, LOADING_MESSAGE)
        remaining = context.time_remaining()
        if remaining is not None and remaining <= 0:
            await context.abort(grpc.StatusCode.DEADLINE_EXCEEDED, "deadline passed before the frame was estimated")
        try:
            return await self._run(self.service.estimate, request)
        except EstimatorError as exc:
            code, message = GRPC_CODES.get(type(exc), grpc.StatusCode.INVALID_ARGUMENT), clip_message(str(exc))
        except Exception:
            log.exception("Estimate failed", extra={"frame_id": request.frame_id, "estimator": echo(request.estimator)})
            code, message = grpc.StatusCode.INTERNAL, INTERNAL_MESSAGE
        await context.abort(code, message)

    async def Track(self, request_iterator, context):
        async for request in request_iterator:
            if self.service is None:
                yield pb.EstimateResponse(frame_id=request.frame_id, capture_time_ns=request.capture_time_ns,
                                          status=pb.EstimateResponse.UNAVAILABLE, message=LOADING_MESSAGE)
                continue
            yield await self._run(self.service.answer, request)

    async def ListEstimators(self, request, context):
        if self.service is None:
            return pb.ListEstimatorsResponse()
        return self.service.list_estimators()
