"""A PoseEstimation servicer that does no work: the baseline the real service is measured against."""

from __future__ import annotations

import grpc

from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc


def _echo(request: pb.EstimateRequest) -> pb.EstimateResponse:
    return pb.EstimateResponse(frame_id=request.frame_id, capture_time_ns=request.capture_time_ns,
                               status=pb.EstimateResponse.OK, pose=pb.Pose(qw=1.0), estimator="echo@0")


class EchoServicer(pb_grpc.PoseEstimationServicer):
    async def Estimate(self, request, context):
        return _echo(request)

    async def Track(self, request_iterator, context):
        async for request in request_iterator:
            yield _echo(request)

    async def ListEstimators(self, request, context):
        return pb.ListEstimatorsResponse(estimators=[pb.EstimatorInfo(name="echo", kind="echo", version="0",
                                                                      ready=True, is_default=True)])


async def start_echo_server(host: str = "127.0.0.1", port: int = 0, max_message_mb: float = 8.0):
    """(started grpc.aio server, bound port)."""
    max_bytes = int(max_message_mb * 1024 * 1024)
    server = grpc.aio.server(options=[("grpc.max_receive_message_length", max_bytes),
                                      ("grpc.max_send_message_length", max_bytes)])
    pb_grpc.add_PoseEstimationServicer_to_server(EchoServicer(), server)
    bound = server.add_insecure_port(f"{host}:{port}")
    await server.start()
    return server, bound
