"""Device slowdown: stretch every frontend operation to emulate a weaker phone (paper Section 4.1).

The paper restricted its device to a Google Pixel 2 by sleeping after each frontend operation so
that it took 3185 / 1294 ~= 2.46 times as long (Geekbench multi-core scores).

Live, `Slowdown.stretch()` measures the real work and sleeps (factor - 1) x its duration.
In replay nothing is measured (a measured time would make two runs differ): the cost of each
operation is modelled by `FrontendCosts` and `Slowdown.virtual_ns(op, count)` gives the stretched
duration to add on the virtual clock.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

PIXEL2_FACTOR = 3185 / 1294  # ~= 2.46


@dataclass(frozen=True)
class FrontendCosts:
    """Modelled raw (unstretched) cost of each frontend operation in ns, for replay.

    Defaults are the paper's stretched timings divided by 2.46 (PIM 0.35 ms, PRM 0.86 ms) and a
    per-sample propagation cost of the order we measure; encoding the request is part of PIM.
    """

    ppm_ns: int = 10_000  # per IMU sample
    pim_ns: int = 142_000  # per frame (PIA check and request building)
    prm_ns: int = 350_000  # per backend response (BSCM and re-propagation)

    def of(self, op: str) -> int:
        try:
            return int(getattr(self, f"{op}_ns"))
        except AttributeError:
            raise ValueError(f"unknown frontend operation {op!r}; expected ppm, pim or prm") from None


class Slowdown:
    def __init__(self, factor: float = PIXEL2_FACTOR, costs: FrontendCosts = FrontendCosts()):
        if factor < 1.0:
            raise ValueError(f"slowdown factor must be >= 1 (1 = no slowdown), got {factor}")
        self.factor = float(factor)
        self.costs = costs

    def virtual_ns(self, op: str, count: int = 1) -> int:
        """Replay: the stretched duration of `count` operations `op` on the virtual clock."""
        return round(self.factor * self.costs.of(op) * count)

    @contextmanager
    def stretch(self) -> Iterator[None]:
        """Live: run the body, then sleep so that it took `factor` times as long."""
        start = time.perf_counter()
        yield
        extra = (self.factor - 1.0) * (time.perf_counter() - start)
        if extra > 0:
            time.sleep(extra)
