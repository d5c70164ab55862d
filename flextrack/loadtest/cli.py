"""`flextrack loadtest`: many simulated devices streaming to a running service; figures, CSV and plots.

    flextrack loadtest --target 127.0.0.1:50051 --clients 40 --fps 30 --duration 10   # default server: pnp
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
    parser.description = (parser.description or "") + (
        ". Exit status: 0 when the run got answers, at most half of them errors (--ramp: a client count passed); "
        "1 when nothing answered, most answers were errors or no --ramp step passed (the reason on stderr); "
        "2 for a bad argument.")
    parser.add_argument("--target", required=True,
                        help="ADDR[,ADDR...]: host:port of the server; several IPv4 addresses are balanced round_robin")
    parser.add_argument("--clients", type=int, default=10, help="simulated devices (one Track stream each)")
    parser.add_argument("--fps", type=float, default=30.0, help="frame rate of each device")
    parser.add_argument("--payload-kb", type=float, default=100.0,
                        help="request size in KiB (image + client state; the paper's 90 kB JPEG + 10 kB state)")
    parser.add_argument("--estimator", default=None,
                        help="estimator name in the server's registry ('' = its default); default: pnp without "
                             "--sequence (the synthetic frames carry the default object's keypoints, which the "
                             "default server config's pnp answers), the server's default with --sequence")
    parser.add_argument("--sequence", type=Path,
                        help="sequence folder whose frame times, intrinsics and rgb/ frames the devices send (an "
                             "oracle answers only a sequence the server has loaded: list its folder in the server "
                             "config's sequence_roots); default: synthetic frames with keypoints")
    parser.add_argument("--duration", type=float, default=10.0,
                        help="seconds measured (after the warm-up); with --answers, the most a run (a ramp step) "
                             "may take")
    parser.add_argument("--answers", type=int, default=0,
                        help="measure until every client has this many answers (after the warm-up) instead of for "
                             "--duration: fewer answers a second on a busy machine, never an empty step "
                             "(default: 0, measure for --duration)")
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
    parser.add_argument("--seed", type=int, default=0, help="seed of the payload bytes, the clients' start offsets and their backoff jitter (default: %(default)s)")


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
                    seed=args.seed, answers=args.answers, metadata=metadata, credentials=credentials, server_name=args.tls_server_name,
                    await_admission=args.await_admission)


def _workload(args: argparse.Namespace):
    from flextrack.loadtest import workload

    if args.sequence:
        return workload.from_sequence(args.sequence, args.payload_kb, args.estimator or "", seed=args.seed)
    return workload.keypoint_frames(args.payload_kb, "pnp" if args.estimator is None else args.estimator, args.fps,
                                    seed=args.seed)


def check_reachable(spec, timeout_s: float = 3.0) -> None:
    """ConnectionError when no server answers at the spec's target within `timeout_s`."""
    import grpc

    from flextrack.loadtest.runner import channel_options, grpc_target
    from flextrack.runners.backends import wait_ready

    target = grpc_target(spec.targets)
    options = channel_options(spec.server_name)
    channel = (grpc.secure_channel(target, spec.credentials, options) if spec.credentials
               else grpc.insecure_channel(target, options))
    try:
        wait_ready(channel, ",".join(spec.targets), timeout_s)
    finally:
        channel.close()


def failure(summary: dict, args: argparse.Namespace) -> str | None:
    """One line saying why the run failed (nothing answered, or most answers were errors), or None."""
    outcomes = {k: v for k, v in summary["outcomes"].items() if k != "OK"}
    if not summary["answered"]:
        return f"nothing answered at {args.target} (sent {summary['sent']} requests)"
    if summary["error_rate"] <= 0.5:
        return None
    worst = max(outcomes, key=outcomes.get)
    hint = {"status:INVALID_INPUT": "does the server have estimator '{e}' and, for an oracle, the --sequence in "
                                    "its config's sequence_roots?",
            "status:OBJECT_NOT_FOUND": "estimator '{e}' found no object in these frames; use frames it can answer "
                                       "(--sequence) or the default (pnp on synthetic keypoints)",
            "grpc:UNAVAILABLE": "is the server still up?",
            "grpc:RESOURCE_EXHAUSTED": "the server refused the streams: fewer --clients or a larger --max-streams"}
    estimator = args.estimator if args.estimator is not None else ("pnp" if not args.sequence else "(default)")
    return (f"{summary['error_rate']:.0%} of {summary['answered']} answers were errors "
            f"({', '.join(f'{k}={v}' for k, v in sorted(outcomes.items()))}); "
            + hint.get(worst, "see load_requests.csv").format(e=estimator))


def run(args: argparse.Namespace) -> int:
    from flextrack.loadtest import ramp, report, runner
    from flextrack.runners import cli_checks

    try:
        for target in args.target.split(","):
            problem = cli_checks.address_problem(target, "--target")
            if problem:
                raise ValueError(problem)
        problem = cli_checks.numbers_problem([
            ("--clients", args.clients, 1, 100_000, True), ("--fps", args.fps, 0, 1000),
            ("--payload-kb", args.payload_kb, 0, 15 * 1024, True), ("--duration", args.duration, 0, 86_400),
            ("--warmup", args.warmup, 0, 3600, True), ("--answers", args.answers, 0, 1_000_000, True),
            ("--channels", args.channels, 0, 100_000, True), ("--p99-bound-ms", args.p99_bound_ms, 0, 3_600_000),
            ("--max-error-rate", args.max_error_rate, 0, 1, True), ("--max-clients", args.max_clients, 1, 100_000, True)])
        if problem:
            raise ValueError(problem)
        spec, work = _spec(args), _workload(args)
        problem = cli_checks.out_folder_problem(args.out)
        if problem:
            raise ValueError(problem)
    except (ValueError, FileNotFoundError, OSError) as exc:
        print(f"flextrack loadtest: {exc}", file=sys.stderr)
        return 2
    try:
        check_reachable(spec)
    except ConnectionError as exc:
        print(f"flextrack loadtest: {exc}", file=sys.stderr)
        return 1
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.ramp:
        summary = report.write_all(runner.run(spec, work), args.out)
        print(report.format_summary(summary))
        print(f"wrote {args.out}/load_summary.json, load_requests.csv, load_latency.png")
        reason = failure(summary, args)
        if reason:
            print(f"flextrack loadtest: {reason}", file=sys.stderr)
            return 1
        return 0

    def show(step: ramp.RampStep) -> None:
        s = step.summary
        if not s["answered"]:
            print(f"  {step.clients:4d} clients: no answers in {s['duration_s']:.1f} s ({s['sent']} requests sent) "
                  "-> fail", flush=True)
            return
        p99 = s["latency_all"]["p99_ms"]
        print(f"  {step.clients:4d} clients: p99 {'-' if p99 is None else f'{p99:.1f}'} ms, "
              f"{s['ok_fps']:.0f} OK/s, errors {s['error_rate']:.1%} of {s['answered']} answers "
              f"-> {'pass' if step.passed else 'fail'}", flush=True)

    best, steps = ramp.ramp(spec, work, args.p99_bound_ms, args.max_error_rate, args.clients, args.max_clients, show)
    ramp.write_ramp(steps, best, args.p99_bound_ms, args.out)
    print(f"largest client count with p99 < {args.p99_bound_ms:g} ms at {args.fps:g} FPS: {best}")
    print(f"wrote {args.out}/ramp.json, ramp.csv, ramp.png")
    if best == 0:  # not even the first step passed: say why, as the single run does
        first = steps[0].summary
        reason = failure(first, args) or (
            f"p99 {first['latency_all']['p99_ms']:.1f} ms is not under --p99-bound-ms {args.p99_bound_ms:g}"
            if first["error_rate"] <= args.max_error_rate else
            f"{first['error_rate']:.1%} of the answers were errors, above --max-error-rate {args.max_error_rate:g}")
        print(f"flextrack loadtest: no client count passed: {steps[0].clients} clients: {reason}", file=sys.stderr)
        return 1
    return 0
