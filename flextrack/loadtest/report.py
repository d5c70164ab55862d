"""Turn a load run's samples into figures: throughput, latency percentiles, outcomes; CSV and a plot."""

from __future__ import annotations

import csv
import json
from collections import Counter
from dataclasses import fields
from pathlib import Path

import numpy as np

from flextrack.loadtest.runner import LoadResult
from flextrack.provenance import provenance


def percentiles(latencies_ms: list[float]) -> dict[str, float | None]:
    if not latencies_ms:
        return {"p50_ms": None, "p95_ms": None, "p99_ms": None, "max_ms": None}
    p50, p95, p99 = np.percentile(latencies_ms, [50, 95, 99])
    return {"p50_ms": float(p50), "p95_ms": float(p95), "p99_ms": float(p99), "max_ms": float(max(latencies_ms))}


def summarize(result: LoadResult) -> dict:
    """Throughput (answers/s, OK answers/s), latency percentiles over all answers and over OK answers,
    the count of each outcome, and the frames clients had to skip."""
    spec, samples = result.spec, result.samples
    outcomes = Counter(s.outcome for s in samples)
    ok = [s.latency_ms for s in samples if s.outcome == "OK"]
    rejected = [s.latency_ms for s in samples if s.outcome in ("grpc:RESOURCE_EXHAUSTED", "status:UNAVAILABLE")]
    window = result.measured_s or spec.duration_s
    return {
        "targets": list(spec.targets), "clients": spec.clients, "fps": spec.fps, "rpc": spec.rpc,
        "duration_s": window, "sent": result.sent, "answered": len(samples), "skipped_frames": result.skipped,
        "offered_fps": spec.clients * spec.fps,
        "throughput_fps": len(samples) / window, "ok_fps": len(ok) / window,
        "error_rate": 1.0 - len(ok) / len(samples) if samples else 1.0,
        "latency_all": percentiles([s.latency_ms for s in samples]),
        "latency_ok": percentiles(ok),
        "latency_rejected": percentiles(rejected),
        "outcomes": dict(sorted(outcomes.items())),
    }


def format_summary(summary: dict) -> str:
    lat, ok = summary["latency_all"], summary["latency_ok"]

    def ms(value):
        return "-" if value is None else f"{value:.1f}"

    lines = [
        (f"{summary['clients']} clients x {summary['fps']:g} FPS ({summary['rpc']}) against "
         f"{','.join(summary['targets'])} for {summary['duration_s']:g} s"),
        (f"  throughput {summary['throughput_fps']:.1f} answers/s ({summary['ok_fps']:.1f} OK/s) of "
         f"{summary['offered_fps']:.0f} offered; {summary['skipped_frames']} frames skipped (request in flight)"),
        (f"  latency all p50/p95/p99 {ms(lat['p50_ms'])}/{ms(lat['p95_ms'])}/{ms(lat['p99_ms'])} ms; "
         f"OK p99 {ms(ok['p99_ms'])} ms"),
        "  outcomes " + ", ".join(f"{k}={v}" for k, v in summary["outcomes"].items()),
    ]
    rej = summary["latency_rejected"]
    if rej["p99_ms"] is not None:
        lines.append(f"  rejected (overload) p50/p99 {ms(rej['p50_ms'])}/{ms(rej['p99_ms'])} ms")
    return "\n".join(lines)


def write_csv(result: LoadResult, path: str | Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["client", "frame", "sent_s", "latency_ms", "outcome"])
        for s in sorted(result.samples, key=lambda s: s.sent_s):
            w.writerow([s.client, s.frame, f"{s.sent_s:.6f}", f"{s.latency_ms:.3f}", s.outcome])


def plot_latency(result: LoadResult, path: str | Path, title: str = "") -> None:
    """Latency of every answer over time, coloured by outcome, with the p99 of each second."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.5))
    by_outcome: dict[str, list] = {}
    for s in result.samples:
        by_outcome.setdefault(s.outcome, []).append((s.sent_s, s.latency_ms))
    for outcome, points in sorted(by_outcome.items()):
        t, lat = np.asarray(points).T
        ax.scatter(t, lat, s=3, alpha=0.4, label=f"{outcome} ({len(points)})")
    if result.samples:
        t = np.array([s.sent_s for s in result.samples])
        lat = np.array([s.latency_ms for s in result.samples])
        seconds = np.arange(int(np.floor(t.min())), int(np.ceil(t.max())) + 1)
        p99 = [np.percentile(lat[(t >= a) & (t < a + 1)], 99) if np.any((t >= a) & (t < a + 1)) else np.nan
               for a in seconds]
        ax.step(seconds + 1, p99, where="pre", color="black", label="p99 per second")
    ax.set_yscale("log")
    ax.set_xlabel("time since start of measurement (s)")
    ax.set_ylabel("latency (ms)")
    spec = result.spec
    ax.set_title(title or f"{spec.clients} clients x {spec.fps:g} FPS ({spec.rpc})")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_all(result: LoadResult, out: str | Path, stem: str = "load") -> dict:
    """summary JSON, per-request CSV and latency plot under `out`; returns the summary."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    summary = summarize(result)
    spec = result.spec
    summary["provenance"] = provenance(**{f.name: getattr(spec, f.name) for f in fields(spec)})
    (out / f"{stem}_summary.json").write_text(json.dumps(summary, indent=2))
    write_csv(result, out / f"{stem}_requests.csv")
    plot_latency(result, out / f"{stem}_latency.png")
    return summary
