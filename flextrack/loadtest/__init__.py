"""Load testing of the PoseEstimation service: simulated devices streaming frames over gRPC."""
