"""Dynamic batching for estimators that have a real batched form (networks), as Triton's dynamic batcher.

Why: a network runs N frames in one call for much less than N times the cost of one. Frames from
different devices arrive independently, so the server holds the first frame at most `max_delay_s`
for others to join, and runs the batch as soon as it has `max_batch` frames or the delay is up.
Under light load a frame waits at most the delay; under heavy load batches fill at once and the
delay costs nothing.

`BatchingEstimator` wraps such an estimator: the service's worker threads call `estimate` as
before and block on their frame's result, while one batcher thread groups them and calls
`estimate_batch`. The service needs at least `max_batch` worker threads for a batch to fill.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from concurrent.futures import Future

from estimators.base import EstimateInput, EstimateOutput, Estimator
from estimators.registry import EstimatorRegistry
from service.metrics import ServiceMetrics

log = logging.getLogger("flextrack.service")


def supports_batching(estimator: Estimator) -> bool:
    """True when the estimator's class overrides the base class's frame-by-frame `estimate_batch`."""
    return type(estimator).estimate_batch is not Estimator.estimate_batch


class BatchingEstimator(Estimator):
    def __init__(self, inner: Estimator, max_batch: int, max_delay_s: float, metrics: ServiceMetrics | None = None):
        if max_batch < 1 or max_delay_s < 0:
            raise ValueError(f"max_batch must be >= 1 and max_delay_s >= 0, got {max_batch}, {max_delay_s}")
        super().__init__(inner.name)
        self.inner, self.max_batch, self.max_delay_s, self.metrics = inner, max_batch, max_delay_s, metrics
        self.kind, self.version = inner.kind, inner.version
        self.uses_image, self.description = inner.uses_image, inner.description
        self._queue: queue.Queue[tuple[EstimateInput, Future] | None] = queue.Queue()
        self._thread = threading.Thread(target=self._loop, name=f"batcher-{inner.name}", daemon=True)
        self._thread.start()

    @property
    def objects(self) -> list[str]:
        return self.inner.objects

    @property
    def ready(self) -> bool:
        return self.inner.ready

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        future: Future = Future()
        self._queue.put((inp, future))
        return future.result()

    def estimate_batch(self, inputs: list[EstimateInput]) -> list[EstimateOutput]:
        return self.inner.estimate_batch(inputs)

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join()

    def _collect(self, first: tuple[EstimateInput, Future]) -> tuple[list, bool]:
        """The batch that starts with `first`, and whether close() was asked for meanwhile."""
        batch, deadline = [first], time.monotonic() + self.max_delay_s
        while len(batch) < self.max_batch:
            try:
                item = self._queue.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                break
            if item is None:
                return batch, True
            batch.append(item)
        return batch, False

    def _loop(self) -> None:
        while (first := self._queue.get()) is not None:
            batch, closing = self._collect(first)
            self._run(batch)
            if closing:
                return

    def _run(self, batch: list[tuple[EstimateInput, Future]]) -> None:
        inputs = [inp for inp, _ in batch]
        if self.metrics:
            self.metrics.observe_batch(self.name, len(batch))
        try:
            outputs = self.inner.estimate_batch(inputs)
            if len(outputs) != len(inputs):
                raise RuntimeError(f"estimate_batch returned {len(outputs)} outputs for {len(inputs)} inputs")
        except Exception:
            # One bad frame must not fail its batch-mates: answer each frame on its own.
            log.debug("batch of %d failed; answering its frames one by one", len(batch), exc_info=True)
            for inp, future in batch:
                try:
                    future.set_result(self.inner.estimate(inp))
                except Exception as exc:  # noqa: BLE001 - handed to the waiting worker, which maps it
                    future.set_exception(exc)
            return
        for (_, future), out in zip(batch, outputs):
            future.set_result(out)


def with_batching(registry: EstimatorRegistry, max_batch: int, max_delay_s: float,
                  metrics: ServiceMetrics | None = None) -> tuple[EstimatorRegistry, list[str]]:
    """A registry whose batch-capable estimators are wrapped in BatchingEstimator, and their names."""
    if max_batch <= 1:
        return registry, []
    wrapped, names = [], []
    for estimator in registry:
        if supports_batching(estimator):
            estimator = BatchingEstimator(estimator, max_batch, max_delay_s, metrics)
            names.append(estimator.name)
        wrapped.append(estimator)
    return EstimatorRegistry(wrapped, registry.default, registry.objects), names
