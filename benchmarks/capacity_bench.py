"""`flextrack bench capacity`: how many 30 FPS devices one server holds with p99 under a bound, against
a no-op echo servicer in the same run, and what the server does at twice that load.

For each backend (the echo servicer, then each estimator of a `flextrack serve` process) the load
generator (loadtest.ramp) searches the largest client count whose p99 stays under the bound. Then
the estimator's server, now started with `--max-streams` set to that capacity (as an operator
would set it from this figure), gets twice its capacity: it must stay up, refuse the excess
devices at once with RESOURCE_EXHAUSTED (they back off and retry, as the SDK does) and keep the
accepted frames' p99 bounded. `--max-queue` bounds each estimator's frame queue besides.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from loadtest import ramp, report, runner, servers, workload

REPO = Path(__file__).resolve().parents[1]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path,
                        help="server config (TOML); default: gt_oracle on a generated toy sequence")
    parser.add_argument("--sequence", type=Path, help="sequence folder the clients send (needed with --config)")
    parser.add_argument("--estimators", default="gt_oracle", help="comma-separated estimator names to measure")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--payload-kb", type=float, default=100.0)
    parser.add_argument("--p99-bound-ms", type=float, default=50.0)
    parser.add_argument("--step-s", type=float, default=4.0, help="measured seconds per ramp step")
    parser.add_argument("--start-clients", type=int, default=4)
    parser.add_argument("--max-clients", type=int, default=512)
    parser.add_argument("--channels", type=int, default=1, help="client channels (0 = one per client)")
    parser.add_argument("--max-queue", type=int, default=8, help="admission bound of the server (--max-queue)")
    parser.add_argument("--workers", type=int, default=4, help="estimator threads of the server (--workers)")
    parser.add_argument("--serve-arg", action="append", default=[], help="extra argument for `flextrack serve`")
    parser.add_argument("--no-overload", action="store_true", help="skip the run at twice the capacity")
    parser.add_argument("--out", type=Path, default=Path("out/bench_capacity"))


def _toy_config(tmp: Path) -> tuple[Path, Path]:
    from benchmarks.toy_sequence import write_orbit_sequence

    seq = write_orbit_sequence(tmp / "orbit", frames=300)
    config = tmp / "capacity.toml"
    config.write_text(f'[server]\ndefault_estimator = "gt_oracle"\n\n[[estimators]]\nname = "gt_oracle"\n'
                      f'kind = "gt_oracle"\n[estimators.params]\nsequence_roots = ["{seq.root}"]\n')
    return config, seq.root


def _ramp(name: str, spec: runner.LoadSpec, work: workload.Workload, args, out: Path) -> dict:
    print(f"{name}: ramp at {args.fps:g} FPS, p99 bound {args.p99_bound_ms:g} ms", flush=True)

    def show(step: ramp.RampStep) -> None:
        lat = step.summary["latency_all"]
        print(f"  {step.clients:4d} clients: {step.summary['ok_fps']:7.0f} OK/s, p50 {lat['p50_ms'] or 0:6.1f} "
              f"p99 {lat['p99_ms'] or 0:7.1f} ms, errors {step.summary['error_rate']:.1%} "
              f"{'pass' if step.passed else 'FAIL'}", flush=True)

    best, steps = ramp.ramp(spec, work, args.p99_bound_ms, 0.01, args.start_clients, args.max_clients, show)
    ramp.write_ramp(steps, best, args.p99_bound_ms, out / name)
    at_best = next((s.summary for s in steps if s.clients == best), None)
    return {"capacity_clients": best, "ok_fps_at_capacity": at_best["ok_fps"] if at_best else 0.0,
            "p99_ms_at_capacity": at_best["latency_all"]["p99_ms"] if at_best else None}


def _overload(name: str, spec: runner.LoadSpec, work: workload.Workload, clients: int, server, out: Path) -> dict:
    result = runner.run(replace(spec, clients=clients), work)
    summary = report.write_all(result, out / name, stem="overload")
    refused = [s.latency_ms for s in result.samples if s.outcome == "grpc:RESOURCE_EXHAUSTED"]
    print(f"{name}: overload at {clients} clients\n{report.format_summary(summary)}", flush=True)
    try:
        servers.wait_serving(server.address, timeout_s=5, process=server.process)
        up = True
    except (RuntimeError, TimeoutError):
        up = False
    return {"clients": clients, "server_up_after": up, "ok_fps": summary["ok_fps"],
            "ok_p99_ms": summary["latency_ok"]["p99_ms"], "rejected_p99_ms": summary["latency_rejected"]["p99_ms"],
            "rejected_max_ms": max(refused) if refused else None,
            "rejected_share": 1 - summary["outcomes"].get("OK", 0) / max(1, summary["answered"]),
            "outcomes": summary["outcomes"]}


def run(args: argparse.Namespace) -> int:
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {"date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "fps": args.fps,
                     "payload_kb": args.payload_kb, "p99_bound_ms": args.p99_bound_ms, "backends": {}}
    with tempfile.TemporaryDirectory() as tmp:
        config, sequence = (args.config, args.sequence) if args.config else _toy_config(Path(tmp))
        if sequence is None:
            print("flextrack bench capacity: --config needs --sequence (the frames the clients send)")
            return 2
        base = runner.LoadSpec(("127.0.0.1:1",), 1, args.fps, args.step_s, 1.0, channels=args.channels)
        echo = servers.start_echo()
        try:
            work = workload.synthetic(args.payload_kb, fps=args.fps)
            results["backends"]["echo"] = _ramp("echo", replace(base, targets=(echo.address,)), work, args, out)
        finally:
            echo.stop()
        serve_args = ["--config", str(config), "--max-queue", str(args.max_queue), "--workers", str(args.workers),
                      "--log-level", "WARNING", *args.serve_arg]
        for name in [n for n in args.estimators.split(",") if n]:
            work = workload.from_sequence(sequence, args.payload_kb, name)
            server = servers.start_serve(serve_args, name, log_path=out / f"{name}_server.log")
            try:
                entry = _ramp(name, replace(base, targets=(server.address,)), work, args, out)
            finally:
                entry["exit_code"] = server.stop()  # 0: a graceful stop
            results["backends"][name] = entry
            if args.no_overload:
                continue
            # The operator's setting from this figure: at most `capacity` devices per replica.
            capacity = max(1, entry["capacity_clients"])
            server = servers.start_serve([*serve_args, "--max-streams", str(capacity)], name,
                                         log_path=out / f"{name}_server.log")
            try:
                entry["overload"] = _overload(name, replace(base, targets=(server.address,)), work, 2 * capacity,
                                              server, out)
            finally:
                entry["overload"]["exit_code"] = server.stop()
    echo_fps = results["backends"]["echo"]["ok_fps_at_capacity"] or float("nan")
    print(f"\n{'backend':<12}{'clients@p99<' + format(args.p99_bound_ms, 'g') + 'ms':>20}{'OK/s':>9}{'vs echo':>9}")
    for name, entry in results["backends"].items():
        if "capacity_clients" in entry:
            entry["fps_vs_echo"] = entry["ok_fps_at_capacity"] / echo_fps
            print(f"{name:<12}{entry['capacity_clients']:>20}{entry['ok_fps_at_capacity']:>9.0f}"
                  f"{entry['fps_vs_echo']:>9.2f}")
    (out / "capacity.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {out}/capacity.json and a ramp per backend")
    return 0
