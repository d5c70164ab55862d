"""Dynamic batching: concurrent frames are grouped up to max_batch, each caller gets its own answer,
one bad frame does not fail its batch-mates, and only estimators with a real batched form are wrapped."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from estimators.base import EstimateInput, EstimateOutput, Estimator, InvalidInput, Status
from estimators.registry import EstimatorRegistry
from service.batching import BatchingEstimator, supports_batching, with_batching
from service.metrics import ServiceMetrics


class NetLike(Estimator):
    """Costs 10 ms a call whatever the batch size (a network's fixed cost); frame id in the answer."""

    kind, version = "netlike", "1"

    def __init__(self):
        super().__init__("net", ["obj"])
        self.batch_sizes: list[int] = []
        self.lock = threading.Lock()

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        return self.estimate_batch([inp])[0]

    def estimate_batch(self, inputs: list[EstimateInput]) -> list[EstimateOutput]:
        if any(inp.frame_id < 0 for inp in inputs):
            raise InvalidInput("negative frame id")
        with self.lock:
            self.batch_sizes.append(len(inputs))
        time.sleep(0.01)
        return [EstimateOutput(Status.OK, np.eye(4), 1.0, message=str(inp.frame_id)) for inp in inputs]


class Plain(Estimator):
    kind = "plain"

    def estimate(self, inp):
        return EstimateOutput(Status.OK, np.eye(4), 1.0)


def test_concurrent_frames_are_batched_and_answered_each_with_its_own_output():
    inner, metrics = NetLike(), ServiceMetrics()
    batcher = BatchingEstimator(inner, max_batch=4, max_delay_s=0.005, metrics=metrics)
    try:
        with ThreadPoolExecutor(8) as pool:
            outputs = list(pool.map(lambda i: batcher.estimate(EstimateInput(frame_id=i, capture_time_ns=0)),
                                    range(40)))
    finally:
        batcher.close()
    assert [o.message for o in outputs] == [str(i) for i in range(40)]
    assert sum(inner.batch_sizes) == 40 and max(inner.batch_sizes) <= 4
    assert max(inner.batch_sizes) > 1  # 8 callers, 10 ms a batch: frames did wait together
    text = "".join(str(s) for m in metrics.registry.collect() for s in m.samples if m.name == "flextrack_batch_size")
    assert "'estimator': 'net'" in text


def test_a_bad_frame_fails_alone():
    inner = NetLike()
    batcher = BatchingEstimator(inner, max_batch=8, max_delay_s=0.05)
    try:
        with ThreadPoolExecutor(4) as pool:
            futures = [pool.submit(batcher.estimate, EstimateInput(frame_id=i, capture_time_ns=0)) for i in (1, -1, 2)]
            assert futures[0].result().message == "1" and futures[2].result().message == "2"
            with pytest.raises(InvalidInput, match="negative"):
                futures[1].result()
    finally:
        batcher.close()


def test_only_batch_capable_estimators_are_wrapped():
    net, plain = NetLike(), Plain("plain", ["obj"])
    assert supports_batching(net) and not supports_batching(plain)
    registry = EstimatorRegistry([plain, net], default="plain")
    wrapped, names = with_batching(registry, max_batch=4, max_delay_s=0.002)
    try:
        assert names == ["net"] and wrapped.default == "plain"
        assert isinstance(wrapped.get("net"), BatchingEstimator) and wrapped.get("plain") is plain
        assert (wrapped.get("net").kind, wrapped.get("net").objects) == ("netlike", ["obj"])
    finally:
        wrapped.get("net").close()
    assert with_batching(registry, max_batch=1, max_delay_s=0.0) == (registry, [])
