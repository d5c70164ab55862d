"""`flextrack bench replicas`: 1, 2 and 3 server processes behind gRPC's client-side round_robin.

The clients use one multi-address target, `ipv4:127.0.0.1:P1,127.0.0.1:P2,...`, with the
round_robin policy, as they would use `dns:///backend:50051` on the headless Kubernetes Service.
Each replica counts what it served on its Prometheus endpoint (`--metrics-port`), so the spread is
measured on the servers, not inferred by the client. Reports throughput against replicas and each
replica's share (even = 1/n).

On a machine with fewer cores than replicas + load generator, throughput cannot grow linearly: the
figure says how far this machine allows.
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
import time
import urllib.request
from pathlib import Path

from flextrack.loadtest import report, runner, servers, workload
from flextrack.provenance import of_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--replicas", default="1,2,3", help="comma-separated replica counts to run")
    parser.add_argument("--clients", type=int, default=24, help="Track streams (a multiple of 6 spreads evenly)")
    parser.add_argument("--fps", type=float, default=1000.0,
                        help="per-client frame rate; the default is closed loop (next frame when the answer is back)")
    parser.add_argument("--payload-kb", type=float, default=100.0, help="request size, kB (default: %(default)g)")
    parser.add_argument("--duration", type=float, default=6.0, help="seconds measured per replica count (default: %(default)g)")
    parser.add_argument("--channels", type=int, default=1,
                        help="client channels the streams share; one channel deals its streams out in turn, while "
                             "0 (one per client) leaves each channel's random first pick to spread them")
    parser.add_argument("--config", type=Path, help="server config; default: gt_oracle on a generated toy sequence")
    parser.add_argument("--sequence", type=Path, help="sequence the clients send (with --config)")
    parser.add_argument("--estimator", default="gt_oracle", help="the estimator the requests name (default: %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("out/bench_replicas"),
                        help="folder for replicas.json and the replicas' logs (default: %(default)s)")


def served(metrics_address: str) -> float:
    """Frames a replica answered, from its /metrics text (any method, estimator and code)."""
    text = urllib.request.urlopen(f"http://{metrics_address}/metrics", timeout=5).read().decode()
    return sum(float(v) for v in re.findall(r"^flextrack_requests_total\{[^}]*\} (\S+)$", text, flags=re.MULTILINE))


def _toy(tmp: Path) -> tuple[Path, Path]:
    from flextrack.benchmarks.capacity_bench import _toy_config

    return _toy_config(tmp)


def run(args: argparse.Namespace) -> int:
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        config, sequence = (args.config, args.sequence) if args.config else _toy(Path(tmp))
        work = workload.from_sequence(sequence, args.payload_kb, args.estimator)
        for n in [int(k) for k in args.replicas.split(",") if k]:
            replicas, metrics = [], []
            try:
                for i in range(n):
                    metrics_port = servers.free_port()
                    replicas.append(servers.start_serve(
                        ["--config", str(config), "--metrics-port", str(metrics_port), "--log-level", "WARNING"],
                        f"replica{i}", log_path=args.out / f"replica{i}.log"))
                    metrics.append(f"127.0.0.1:{metrics_port}")
                before = [served(m) for m in metrics]
                spec = runner.LoadSpec(tuple(r.address for r in replicas), args.clients, args.fps, args.duration,
                                       warmup_s=1.0, channels=args.channels)
                summary = report.summarize(runner.run(spec, work))
                counts = [served(m) - b for m, b in zip(metrics, before)]
            finally:
                for r in replicas:
                    r.stop()
            shares = [c / sum(counts) for c in counts] if sum(counts) else [0.0] * n
            worst = max(abs(s * n - 1) for s in shares)  # largest deviation from an even share, relative
            rows.append({"replicas": n, "ok_fps": summary["ok_fps"], "p50_ms": summary["latency_all"]["p50_ms"],
                         "p99_ms": summary["latency_all"]["p99_ms"], "served": counts, "shares": shares,
                         "max_deviation_from_even": worst, "outcomes": summary["outcomes"]})
            print(f"{n} replica(s): {summary['ok_fps']:7.0f} OK/s, p50 {summary['latency_all']['p50_ms']:.1f} ms, "
                  f"p99 {summary['latency_all']['p99_ms']:.1f} ms, shares "
                  f"{', '.join(f'{s:.3f}' for s in shares)} (max {worst:.1%} off even)", flush=True)
    base = rows[0]["ok_fps"] or float("nan")
    for row in rows:
        row["speedup_vs_first"] = row["ok_fps"] / base
    result = {"date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "clients": args.clients,
              "fps": args.fps, "payload_kb": args.payload_kb, "rows": rows,
              "provenance": of_args(args, command="flextrack bench replicas")}
    (args.out / "replicas.json").write_text(json.dumps(result, indent=2))
    print("throughput vs replicas: " + ", ".join(f"{r['replicas']}: x{r['speedup_vs_first']:.2f}" for r in rows))
    return 0
