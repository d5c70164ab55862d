"""Backends a runner talks to, and the oracle registry it serves a sequence with.

A replay backend answers one request at a time and says how long the link took in virtual time:
`call(request) -> (response, LinkDelays)`.

- `GrpcBackend`: a real `Track` stream to a server (the runner's own `BackgroundServer` on a
  loopback port, or any address) through the `LatencyInterceptor` in replay mode, which stamps
  the sampled delays;
- `InProcessBackend`: the service's `EstimationService` called directly, delays drawn from the
  same network model, so both give bit-identical runs.
"""

from __future__ import annotations

import queue
from pathlib import Path

import grpc

from client_sdk import network_model
from client_sdk.interceptor import LatencyInterceptor
from client_sdk.network_model import LinkDelays, NetworkOptions
from estimators.gt_oracle import GtOracleEstimator
from estimators.registry import EstimatorRegistry
from flextrack.formats.sequence import Sequence
from flextrack.v1 import pose_estimation_pb2 as pb
from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
from service.estimation import EstimationService

# The paper gives no sigma for its "Noisy" backend; these reproduce its error scale (DESIGN.md).
NOISY_T_M = 0.003
NOISY_R_DEG = 0.3
ORACLE_BACKENDS = ("gt", "noisy")


def oracle_registry(sequence_roots: list, noise_seed: int = 0) -> EstimatorRegistry:
    """Estimators "gt" (exact) and "noisy" (3 mm, 0.3 deg per axis) over the given sequences: folders (or
    folders of them), or sequences already loaded (`Sequence`, with their whole ground truth: not parsed again)."""
    loaded = [s for s in sequence_roots if isinstance(s, Sequence)]
    roots = [Path(r) for r in sequence_roots if not isinstance(r, Sequence)]
    oracles = [GtOracleEstimator("gt", roots),
               GtOracleEstimator("noisy", roots, noise_t_m=NOISY_T_M, noise_r_deg=NOISY_R_DEG, seed=noise_seed)]
    for oracle in oracles:
        for seq in loaded:
            oracle.add_sequence(seq)
    return EstimatorRegistry(oracles, default="gt")


def wait_ready(channel: grpc.Channel, address: str, timeout_s: float = 3.0) -> None:
    """ConnectionError, saying what to do, when the channel to `address` is not ready within `timeout_s`."""
    try:
        grpc.channel_ready_future(channel).result(timeout=timeout_s)
    except grpc.FutureTimeoutError:
        raise ConnectionError(f"nothing answered at {address} within {timeout_s:g} s; start a server there "
                              "(`flextrack serve --port PORT`) or check the address") from None


class InProcessBackend:
    def __init__(self, registry: EstimatorRegistry, network: NetworkOptions):
        self.service = EstimationService(registry)
        self.network = network

    def call(self, request: pb.EstimateRequest) -> tuple[pb.EstimateResponse, LinkDelays]:
        response = self.service.answer(request)
        return response, network_model.sample(self.network, request.frame_id, request.ByteSize(),
                                              response.ByteSize())

    def close(self) -> None:
        pass


class GrpcBackend:
    """One `Track` stream, used synchronously: send a request, wait for its response."""

    def __init__(self, address: str, network: NetworkOptions, timeout_s: float = 30.0):
        self.interceptor = LatencyInterceptor(network, live=False)
        self._channel = grpc.insecure_channel(address)
        try:
            wait_ready(self._channel, address, timeout_s)
        except ConnectionError:
            self._channel.close()
            raise
        stub = pb_grpc.PoseEstimationStub(grpc.intercept_channel(self._channel, self.interceptor))
        self._outbox: queue.Queue = queue.Queue()
        self._responses = stub.Track(iter(self._outbox.get, None))

    def call(self, request: pb.EstimateRequest) -> tuple[pb.EstimateResponse, LinkDelays]:
        self._outbox.put(request)
        response = next(self._responses)
        return response, self.interceptor.pop_stamp(request.frame_id)

    def close(self) -> None:
        self._outbox.put(None)
        self._responses.cancel()
        self._channel.close()
