"""The paper's network model (Section 4.1, "Networking and Transmission") as a seeded pure function.

The paper computes one round trip as

    t = 100 kB * 8 / (1024 * 50 Mbps) * 1e3 + 10 ms * 2 + U(0, 30) ms  ~=  (35, 66) ms

i.e. 15.625 ms of transmission for 100 kB, 20 ms of propagation and a uniform extra delay.
Its arithmetic divides kilobits by 1024 to get megabits, so we count in binary units throughout:
1 kB = 1024 bytes, 1 Mb = 1024 * 1024 bits; 50 Mbps = 50 * 2**20 bit/s. A real payload of
102,400 bytes (= 100 kB) then costs exactly the paper's 15.625 ms.

Split over the two legs: the uplink carries the request (its serialized size with
`fixed_payload_bytes=None`, or the paper's fixed 100 kB, the default, which the paper's own
experiments keep: their requests carry a stand-in of its 90 kB JPEG), one propagation delay and the
extra delay. Runners that send real frames charge their real size: once the device tracks it sends
the crop around its prior (client_sdk.crop), about 20 kB a request with the ~10 kB state; the downlink carries the response (a pose of
about 100 bytes, which the paper neglects: `count_downlink_payload=False` reproduces it exactly)
and the other propagation delay.

Each draw is a pure function of (seed, key) with key the request's frame id, so replay and live
runs agree and the order in which threads ask does not matter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

KB_BYTES = 1024
MB_BITS = 1024 * 1024
PAPER_PAYLOAD_BYTES = 100 * KB_BYTES  # 90 kB JPEG + 10 kB state


@dataclass(frozen=True)
class NetworkOptions:
    bandwidth_mbps: float = 50.0  # paper: 5G minimum
    propagation_ms: float = 10.0  # each way
    extra_max_ms: float = 30.0  # extra delay ~ U(0, extra_max_ms), once per round trip
    fixed_payload_bytes: int | None = PAPER_PAYLOAD_BYTES  # None: each request's real size (frames or crops)
    count_downlink_payload: bool = False  # the paper neglects the response's size
    seed: int = 0

    def __post_init__(self) -> None:
        if self.bandwidth_mbps <= 0:
            raise ValueError(f"bandwidth_mbps must be > 0, got {self.bandwidth_mbps}")
        if self.propagation_ms < 0 or self.extra_max_ms < 0:
            raise ValueError("propagation_ms and extra_max_ms must be >= 0")
        if self.fixed_payload_bytes is not None and self.fixed_payload_bytes < 0:
            raise ValueError("fixed_payload_bytes must be >= 0 or None")

    @classmethod
    def zero(cls) -> NetworkOptions:
        """No network at all (infinite bandwidth, no delays): the latency-free baseline."""
        return cls(bandwidth_mbps=float("inf"), propagation_ms=0.0, extra_max_ms=0.0, fixed_payload_bytes=0)


@dataclass(frozen=True)
class LinkDelays:
    uplink_ns: int
    downlink_ns: int

    @property
    def round_trip_ns(self) -> int:
        return self.uplink_ns + self.downlink_ns


def transmission_ns(payload_bytes: int, bandwidth_mbps: float) -> int:
    """Time to push `payload_bytes` through the link, in the paper's binary units."""
    return round(payload_bytes * 8 / (bandwidth_mbps * MB_BITS) * 1e9)


def extra_delay_ns(opts: NetworkOptions, key: int) -> int:
    """The uniform extra delay for request `key`: a pure function of (seed, key)."""
    if opts.extra_max_ms == 0:
        return 0
    rng = np.random.default_rng([int(opts.seed) & 0xFFFFFFFF, int(key) & 0xFFFFFFFFFFFFFFFF])
    return round(rng.uniform(0.0, opts.extra_max_ms) * 1e6)


def sample(opts: NetworkOptions, key: int, request_bytes: int, response_bytes: int = 0) -> LinkDelays:
    """Uplink and downlink delays (ns) of request `key` carrying `request_bytes`."""
    up_bytes = request_bytes if opts.fixed_payload_bytes is None else opts.fixed_payload_bytes
    down_bytes = response_bytes if opts.count_downlink_payload else 0
    prop = round(opts.propagation_ms * 1e6)
    return LinkDelays(
        uplink_ns=transmission_ns(up_bytes, opts.bandwidth_mbps) + prop + extra_delay_ns(opts, key),
        downlink_ns=transmission_ns(down_bytes, opts.bandwidth_mbps) + prop,
    )
