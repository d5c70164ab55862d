"""`flextrack demo --out out/demo`: the whole system, live, on a fresh machine.

1. simulate (seeded) a short sequence: the paper's circular/medium program at 120 FPS with a
   Pixel-2-grade IMU;
2. start a backend on a loopback port with the service's embedded default config
   (`service/default_config.toml`: the "gt_oracle" and "gt_noisy" oracles, given that sequence);
3. track it LIVE (tracker options `--tracker`, default "filter"): IMU and frames fed in real time, requests over the `Track` stream through the
   latency interceptor (50 Mbps, 10 ms each way, U(0, 30) ms, 100 kB a request) with the Pixel 2
   slowdown, a progress line while it runs;
4. replay the same sequence in virtual time with both backends, for comparison;
5. print the error table and write plots, per-frame CSVs and TUM trajectories, and `demo.json`: every
   run's summary with the provenance. The README's demo table is generated from a stored copy of it
   (docs/results/demo/, `flextrack report`), and a test replays the same rows to check it to the digit.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict
from pathlib import Path

from client_sdk.network_model import NetworkOptions
from client_sdk.options import PRESETS, preset
from client_sdk.slowdown import PIXEL2_FACTOR
from flextrack.formats import sequence as sequence_io
from flextrack.provenance import of_args
from flextrack.runners import session
from flextrack.runners.cli_checks import numbers_problem, out_folder_problem
from flextrack.runners.results import format_table

MIN_DURATION_S = 3.0  # the motion programs ease in over 2 s
# --backend choice -> estimator name in the service's default config
BACKENDS = {"gt": "gt_oracle", "noisy": "gt_noisy"}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder")
    parser.add_argument("--motion", choices=("circular", "translational"), default="circular",
                        help="the paper's motion program (default: %(default)s)")
    parser.add_argument("--level", choices=("easy", "medium", "hard"), default="medium",
                        help="the program's speed level (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=12.0,
                        help=f"seconds of motion (after a still start), at least {MIN_DURATION_S:g}")
    parser.add_argument("--fps", type=float, default=120.0, help="camera frame rate, Hz (default: %(default)g)")
    parser.add_argument("--backend", choices=("gt", "noisy"), default="noisy", help="backend of the live run")
    parser.add_argument("--seed", type=int, default=0, help="simulation and backend-noise seed (default: %(default)s)")
    parser.add_argument("--tracker", choices=PRESETS, default="filter",
                        help="tracker: 'filter' (the error-state Kalman filter) or 'paper' (resets to each backend "
                             "pose as the paper does) (default: %(default)s)")
    parser.add_argument("--no-replay", action="store_true", help="only the live run")


def simulate(out: Path, args) -> Path:
    from flextrack.simulator.generate import generate_sequence  # the sim extra

    root = out / f"sequence_{args.motion}_{args.level}_{args.fps:g}fps_{args.duration:g}s_seed{args.seed}"
    if not (root / "rig.yaml").is_file():
        generate_sequence(args.motion, args.level, root, duration_s=args.duration, fps=args.fps, seed=args.seed)
    return root


def default_registry(seq):
    """The embedded server's estimators: the default config, its oracles given this sequence."""
    from service.cli import DEFAULT_CONFIG  # the server extra

    return session.registry_for(seq, session.RunSpec(config=DEFAULT_CONFIG))


def replay_runs(seq, tracker_options, network: NetworkOptions, registry) -> list[tuple[str, object]]:
    """("replay, gt" | "replay, noisy", TrackRecord) in virtual time: bit-identical for one seed, which is
    what lets the README's stored rows be checked against a fresh replay."""
    return [(f"replay, {backend}", session.track(seq, tracker_options, session.RunSpec(backend=estimator,
                                                                                        network=network),
                                                 registry=registry))
            for backend, estimator in BACKENDS.items()]


def write_result(out: Path, args, summaries: list[tuple[str, object]], wall_s: float) -> Path:
    """`demo.json`: the provenance (options, seed, commit, date) and each run's summary, as printed."""
    record = of_args(args, command="flextrack demo")
    record["wall_s"] = round(wall_s, 1)
    path = out / "demo.json"
    path.write_text(json.dumps({"provenance": record, "runs": [{"run": name, "summary": asdict(summary)}
                                                                for name, summary in summaries]}, indent=1) + "\n")
    return path


def run(args) -> int:
    problem = numbers_problem([("--duration", args.duration, MIN_DURATION_S, 3600, True),
                               ("--fps", args.fps, 0, 1000)]) or out_folder_problem(args.out)
    if problem:
        print(f"flextrack demo: {problem}", file=sys.stderr)
        return 2
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    try:
        print(f"[1/4] simulating {args.motion}/{args.level}, {args.duration:g} s at {args.fps:g} FPS (seed {args.seed})")
        seq = sequence_io.load(simulate(out, args))
    except (ValueError, FileNotFoundError) as exc:
        print(f"flextrack demo: cannot simulate the sequence: {exc}", file=sys.stderr)
        return 2
    from service.cli import DEFAULT_CONFIG  # the server extra

    try:
        registry = default_registry(seq)
    except (ValueError, FileNotFoundError) as exc:
        print(f"flextrack demo: cannot load the default backend config {DEFAULT_CONFIG}: {exc}", file=sys.stderr)
        return 2
    network = NetworkOptions(seed=args.seed)
    tracker_options = preset(args.tracker)
    print(f"[2/4] backend on loopback, {DEFAULT_CONFIG.name}: estimators {registry.names()}")
    print(f"      network: {network.bandwidth_mbps:g} Mbps, {network.propagation_ms:g} ms each way, "
          f"U(0, {network.extra_max_ms:g}) ms extra, {network.fixed_payload_bytes // 1024} kB a request; "
          f"device slowdown x{PIXEL2_FACTOR:.2f} (Pixel 2)")
    print(f"[3/4] tracking LIVE over gRPC ({args.backend} backend), {len(seq.frame_ids)} frames, "
          f"{len(seq.imu.t_ns)} IMU samples")
    runs = []
    try:
        live = session.track(seq, tracker_options, session.RunSpec(backend=BACKENDS[args.backend], network=network,
                                                                   live=True),
                             progress=session.print_progress, registry=registry)
        runs.append((f"live, {args.backend}", live))
        if not args.no_replay:
            print("[4/4] replaying in virtual time (bit-identical for one seed) with both backends")
            runs += replay_runs(seq, tracker_options, network, registry)
    except (ConnectionError, RuntimeError) as exc:
        print(f"\nflextrack demo: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("\nflextrack demo: interrupted", file=sys.stderr)
        return 130
    print()
    summaries = [(name, record.summarize()) for name, record in runs]
    print(format_table(summaries))
    result = write_result(out, args, summaries, time.perf_counter() - started)
    written = []
    for name, record in runs:
        stem = name.replace(", ", "_")
        record.write(out, stem)
        written += session.write_plots(record, out, stem)
    print(f"\nplots: {', '.join(str(p) for p in written[:2])} (and {len(written) - 2} more); per-frame CSV, "
          f"summary and TUM trajectories in {out}/, every run's summary in {result}  "
          f"({time.perf_counter() - started:.0f} s)")
    return 0
