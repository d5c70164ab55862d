"""`flextrack bench NAME ...`: benchmarks that print figures. Each is a module in BENCHMARKS exposing
`add_arguments(parser)` and `run(args) -> int`; add yours to the table."""

from __future__ import annotations

import argparse
import importlib

# name -> (module, one-line help)
BENCHMARKS: dict[str, tuple[str, str]] = {
    "capacity": ("flextrack.benchmarks.capacity_bench", "30 FPS clients with p99 under a bound, vs echo, and 2x overload"),
    "replicas": ("flextrack.benchmarks.replicas_bench", "1-3 server processes behind gRPC round_robin: spread and throughput"),
    "batching": ("flextrack.benchmarks.batching_bench", "dynamic batching on/off for a batch-capable estimator (pvnet)"),
    "container": ("flextrack.benchmarks.container_check", "build the Dockerfile with container-check and check the image serves"),
    "tracker": ("flextrack.benchmarks.tracker_bench", "tracker core: PIM/PRM per call and PPM per IMU sample (--accuracy: the paper core's accuracy tables)"),
    "pvnet": ("flextrack.benchmarks.pvnet_bench", "pvnet estimator: decode/inference/voting/PnP ms, frames/s per batch"),
    "region": ("flextrack.benchmarks.region_bench", "region estimator: CPU ms a frame, and the service's frames/s with it"),
    "service": ("flextrack.benchmarks.service_bench", "Track stream and unary Estimate: gt_oracle vs a no-op echo servicer"),
    "sdk-memory": ("flextrack.benchmarks.sdk_memory_bench", "the client SDK's RSS and buffer sizes over a long live run"),
    "jpeg-bound": ("flextrack.benchmarks.jpeg_bound_bench", "worst JPEG decode the service's scan and header checks let in"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="benchmark", metavar="BENCHMARK", required=True)
    for name, (module_name, help_text) in BENCHMARKS.items():
        bench_parser = sub.add_parser(name, help=help_text, description=help_text,
                                      formatter_class=argparse.ArgumentDefaultsHelpFormatter)
        importlib.import_module(module_name).add_arguments(bench_parser)


def run(args: argparse.Namespace) -> int:
    return int(importlib.import_module(BENCHMARKS[args.benchmark][0]).run(args) or 0)
