"""The PoseEstimation servicer: a thin grpc.aio layer over EstimationService.

Estimator calls run in a thread pool so that the event loop keeps serving other streams while
one frame is being estimated; only estimators marked `cheap` are called on the loop itself. A thread
cannot be stopped: when the server stops, the calls still waiting for theirs end UNAVAILABLE
(`abandon`) and the threads are left behind with the process.
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
STOPPING_MESSAGE = "the server is shutting down; send the frame to another"


class ServerStopping(Exception):
    """The server stopped waiting for the call's estimator thread."""


class PoseEstimationServicer(pb_grpc.PoseEstimationServicer):
    def __init__(self, executor: Executor, service: EstimationService | None = None):
        self.executor = executor
        self.service = service  # None until the estimators have loaded
        self.running_after_cancel = 0  # cancelled calls whose estimator thread still works on their frame
        self.stopping = False  # set by `abandon`: no call waits for its thread any more
        self._watches: set[asyncio.Future] = set()  # what calls wait on now (`_watch`)

    def abandon(self) -> None:
        """End every call still waiting for its estimator thread (UNAVAILABLE, or CANCELLED for one its client
        cancelled), now and from now on: the server is stopping and must not wait for threads that cannot be
        stopped (grpc.aio would cancel the calls at the end of its grace, and log each as an error)."""
        self.stopping = True
        for watch in list(self._watches):
            if not watch.done():
                watch.set_exception(ServerStopping())

    def _watch(self, work: asyncio.Future) -> asyncio.Future:
        """A future that ends as `work` does, or with ServerStopping when the server abandons its calls;
        cancelling it leaves `work` running."""
        watch = work.get_loop().create_future()
        if self.stopping:
            watch.set_exception(ServerStopping())
            return watch

        def settle(done: asyncio.Future) -> None:
            if watch.done():
                return
            if done.cancelled():
                watch.cancel()
            elif done.exception() is not None:
                watch.set_exception(done.exception())
            else:
                watch.set_result(done.result())

        work.add_done_callback(settle)
        self._watches.add(watch)
        watch.add_done_callback(self._watches.discard)
        return watch

    async def _run(self, fn, request):
        if self.service.is_cheap(request):
            return fn(request)
        work = asyncio.get_running_loop().run_in_executor(self.executor, fn, request)
        try:
            return await self._watch(work)
        except asyncio.CancelledError:
            # The call is gone (the client cancelled it, or its deadline passed), but a thread cannot be stopped:
            # hold the call until its work really ends, so that the admission bound, which frees the call's slot
            # when the call ends, keeps counting the thread that still runs, then end it as cancelled.
            self.running_after_cancel += 1
            try:
                while not work.done():
                    try:
                        await self._watch(work)
                    except asyncio.CancelledError:
                        continue  # cancelled again: the work still holds its thread
                    except Exception:  # noqa: BLE001 - the answer nobody waits for any more, or the server stops
                        break
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
        except ServerStopping:
            code, message = grpc.StatusCode.UNAVAILABLE, STOPPING_MESSAGE
        except EstimatorError as exc:
            code, message = GRPC_CODES.get(type(exc), grpc.StatusCode.INVALID_ARGUMENT), clip_message(str(exc))
        except Exception:
            log.exception("Estimate failed", extra={"frame_id": request.frame_id, "estimator": echo(request.estimator)})
            code, message = grpc.StatusCode.INTERNAL, INTERNAL_MESSAGE
        await context.abort(code, message)

    async def Track(self, request_iterator, context):
        try:
            async for request in request_iterator:
                if self.stopping:
                    break
                if self.service is None:
                    yield pb.EstimateResponse(frame_id=request.frame_id, capture_time_ns=request.capture_time_ns,
                                              status=pb.EstimateResponse.UNAVAILABLE, message=LOADING_MESSAGE)
                    continue
                try:
                    answer = await self._run(self.service.answer, request)
                except ServerStopping:
                    break
                yield answer
            else:
                return  # the device ended its stream
        except asyncio.CancelledError:
            if not self.stopping:
                raise
            return  # gRPC ends the streams still open at the end of the stop: quietly, the process is leaving
        # the server is stopping: the stream ends UNAVAILABLE, its frame in flight unanswered (the device's
        # client fails it over to another server)
        await context.abort(grpc.StatusCode.UNAVAILABLE, STOPPING_MESSAGE)

    async def ListEstimators(self, request, context):
        if self.service is None:
            return pb.ListEstimatorsResponse()
        return self.service.list_estimators()
