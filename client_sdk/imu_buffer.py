"""The IMU samples kept for re-propagation, each with the state propagated up to it.

A sample is a tuple `(t_ns, wx, wy, wz, ax, ay, az)`; its state is the nominal tuple (see
`client_sdk.state`) at `t_ns`, or None while the tracker is not initialised. Plain lists with
amortised trimming keep appends O(1) and lookups a `bisect`.
"""

from __future__ import annotations

from bisect import bisect_right


class ImuBuffer:
    def __init__(self, keep_ns: int) -> None:
        self.keep_ns = int(keep_ns)
        self.times: list[int] = []
        self.samples: list[tuple] = []
        self.states: list[tuple | None] = []

    def __len__(self) -> int:
        return len(self.times)

    @property
    def last_t_ns(self) -> int | None:
        return self.times[-1] if self.times else None

    @property
    def first_t_ns(self) -> int | None:
        return self.times[0] if self.times else None

    def append(self, sample: tuple, state: tuple | None) -> None:
        """Add the newest sample; drop, in chunks, samples older than `keep_ns` before it."""
        self.times.append(sample[0])
        self.samples.append(sample)
        self.states.append(state)
        horizon = sample[0] - self.keep_ns
        if self.times[0] < horizon - self.keep_ns // 2:
            cut = bisect_right(self.times, horizon)
            del self.times[:cut], self.samples[:cut], self.states[:cut]

    def index_at_or_before(self, t_ns: int) -> int:
        """Index of the last sample with time <= t_ns, -1 if none."""
        return bisect_right(self.times, t_ns) - 1

    def window(self, t_from_ns: int, t_to_ns: int) -> list[tuple]:
        """Samples with t_from_ns < t <= t_to_ns."""
        return self.samples[bisect_right(self.times, t_from_ns): bisect_right(self.times, t_to_ns)]

    def recent(self, n: int) -> tuple[list[int], list[tuple]]:
        """Times and samples of the newest n samples."""
        return (self.times[-n:], self.samples[-n:]) if n > 0 else ([], [])
