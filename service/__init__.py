"""The PoseEstimation gRPC backend: request decoding, the estimation service, the grpc.aio server."""
