"""`flextrack loadtest`: many simulated devices streaming to a running service; figures, CSV and plots.

    flextrack loadtest --target 127.0.0.1:50051 --clients 20 --fps 30 --payload-kb 100 \\
        --estimator gt_oracle --sequence SEQ_DIR --duration 10 --out out/load
    flextrack loadtest --target 127.0.0.1:50051,127.0.0.1:50052 --ramp --p99-bound-ms 50 ...

Built on grpc.aio rather than locust; flextrack/loadtest/runner.py says why.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--target", required=True,
                        help="ADDR[,ADDR...]: host:port of the server; several IPv4 addresses are balanced round_robin")
    parser.add_argument("--clients", type=int, default=10, help="simulated devices (one Track stream each)")
    parser.add_argument("--fps", type=float, default=30.0, help="frame rate of each device")
    parser.add_argument("--payload-kb", type=float, default=100.0,
                        help="request size in KiB (image + client state; the paper's 90 kB JPEG + 10 kB state)")
    parser.add_argument("--estimator", default="", help="estimator name in the server's registry ('' = its default)")
    parser.add_argument("--sequence", type=Path,
                        help="sequence folder whose frame times, intrinsics and rgb/ frames the devices send "
                             "(an oracle needs the one it has loaded); default: synthetic frames")
    parser.add_argument("--duration", type=float, default=10.0, help="seconds measured (after the warm-up)")
    parser.add_argument("--warmup", type=float, default=1.0, help="seconds before measuring starts")
    parser.add_argument("--rpc", choices=["track", "estimate"], default="track",
                        help="Track streams (the device's path) or unary Estimate calls")
    parser.add_argument("--channels", type=int, default=1,
                        help="gRPC channels the clients share (0 = one per client, as separate devices have)")
    parser.add_argument("--await-admission", action="store_true",
                        help="wait for a new stream's admission (a flextrack server's initial metadata) before its "
                             "first frame; needed to see refusals under --max-streams as RESOURCE_EXHAUSTED")
    parser.add_argument("--ramp", action="store_true",
                        help="find the largest --clients whose p99 stays under --p99-bound-ms (--clients is the start)")
    parser.add_argument("--p99-bound-ms", type=float, default=50.0, help="latency bound of --ramp")
    parser.add_argument("--max-error-rate", type=float, default=0.01,
                        help="--ramp: largest share of non-OK answers a passing step may have")
    parser.add_argument("--max-clients", type=int, default=512, help="--ramp: stop doubling here")
    parser.add_argument("--token-file", type=Path, help="bearer token (first token of the file) to send")
    parser.add_argument("--tls-ca", type=Path, help="connect with TLS, trusting this CA (PEM)")
    parser.add_argument("--tls-server-name", help="name to check in the server's certificate")
    parser.add_argument("--out", type=Path, default=Path("out/loadtest"), help="folder for JSON, CSV and PNG")
    parser.add_argument("--seed", type=int, default=0)


def _spec(args: argparse.Namespace):
    from flextrack.loadtest.runner import LoadSpec

    metadata, credentials = (), None
    if args.token_file or args.tls_ca:
        from client_sdk import credentials as creds
        from service.security import load_tokens

        token = load_tokens(args.token_file)[0] if args.token_file else None
        if args.tls_ca:
            credentials = creds.channel_credentials(args.tls_ca, token=token)
        elif token:
            metadata = creds.token_metadata(token)
    targets = tuple(t for t in args.target.split(",") if t.strip())
    return LoadSpec(targets, args.clients, args.fps, args.duration, args.warmup, args.rpc, args.channels,
                    seed=args.seed, metadata=metadata, credentials=credentials, server_name=args.tls_server_name,
                    await_admission=args.await_admission)


def _workload(args: argparse.Namespace):
    from flextrack.loadtest import workload

    if args.sequence:
        return workload.from_sequence(args.sequence, args.payload_kb, args.estimator, seed=args.seed)
    return workload.synthetic(args.payload_kb, args.estimator, args.fps, seed=args.seed)


def run(args: argparse.Namespace) -> int:
    from flextrack.loadtest import ramp, report, runner

    try:
        spec, work = _spec(args), _workload(args)
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"flextrack loadtest: {exc}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.ramp:
        summary = report.write_all(runner.run(spec, work), args.out)
        print(report.format_summary(summary))
        print(f"wrote {args.out}/load_summary.json, load_requests.csv, load_latency.png")
        return 0 if summary["answered"] else 1

    def show(step: ramp.RampStep) -> None:
        p99 = step.summary["latency_all"]["p99_ms"]
        print(f"  {step.clients:4d} clients: p99 {'-' if p99 is None else f'{p99:.1f}'} ms, "
              f"{step.summary['ok_fps']:.0f} OK/s, errors {step.summary['error_rate']:.1%} "
              f"-> {'pass' if step.passed else 'fail'}", flush=True)

    best, steps = ramp.ramp(spec, work, args.p99_bound_ms, args.max_error_rate, args.clients, args.max_clients, show)
    ramp.write_ramp(steps, best, args.p99_bound_ms, args.out)
    print(f"largest client count with p99 < {args.p99_bound_ms:g} ms at {args.fps:g} FPS: {best}")
    print(f"wrote {args.out}/ramp.json, ramp.csv, ramp.png")
    return 0
