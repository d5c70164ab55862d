"""Capacity search: the largest number of clients whose p99 latency stays under a bound.

Doubles the client count until a step fails, then bisects between the last pass and the first
fail. A step passes when the p99 of all answers is under the bound and at most `max_error_rate` of
the answers are not OK (an overloaded server that rejects fast would otherwise look healthy).
"""

from __future__ import annotations

import csv
import json
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

from flextrack.loadtest.report import summarize
from flextrack.loadtest.runner import LoadSpec, run
from flextrack.loadtest.workload import Workload
from flextrack.provenance import provenance


@dataclass(frozen=True)
class RampStep:
    clients: int
    summary: dict
    passed: bool


def passes(summary: dict, p99_bound_ms: float, max_error_rate: float) -> bool:
    p99 = summary["latency_all"]["p99_ms"]
    return p99 is not None and p99 < p99_bound_ms and summary["error_rate"] <= max_error_rate


def ramp(spec: LoadSpec, workload: Workload, p99_bound_ms: float, max_error_rate: float = 0.01,
         start: int = 1, max_clients: int = 1024,
         on_step: Callable[[RampStep], None] | None = None) -> tuple[int, list[RampStep]]:
    """(largest passing client count or 0, every step run, in order)."""
    steps: list[RampStep] = []

    def trial(n: int) -> bool:
        summary = summarize(run(replace(spec, clients=n), workload))
        step = RampStep(n, summary, passes(summary, p99_bound_ms, max_error_rate))
        steps.append(step)
        if on_step:
            on_step(step)
        return step.passed

    good, bad = 0, None
    n = max(1, start)
    while n <= max_clients:
        if not trial(n):
            bad = n
            break
        good, n = n, n * 2
    if bad is None:
        return good, steps
    while bad - good > 1 and bad - good > max(1, good // 16):  # to about 6 %: finer is below the noise
        mid = (good + bad) // 2
        if trial(mid):
            good = mid
        else:
            bad = mid
    return good, steps


def write_ramp(steps: list[RampStep], best: int, p99_bound_ms: float, out: str | Path) -> None:
    """ramp.json (every step's summary), ramp.csv (one row a step) and ramp.png (p99 against clients)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "ramp.json").write_text(json.dumps({"best_clients": best, "p99_bound_ms": p99_bound_ms,
                                               "steps": [s.summary | {"passed": s.passed} for s in steps],
                                               "provenance": provenance(p99_bound_ms=p99_bound_ms,
                                                                        clients=[s.clients for s in steps])}, indent=2))
    with open(out / "ramp.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["clients", "answered", "ok_fps", "p50_ms", "p95_ms", "p99_ms", "error_rate", "passed"])
        for s in sorted(steps, key=lambda s: s.clients):
            lat = s.summary["latency_all"]
            error_rate = f"{s.summary['error_rate']:.4f}" if s.summary["answered"] else ""  # no answers: no rate
            w.writerow([s.clients, s.summary["answered"], f"{s.summary['ok_fps']:.1f}", lat["p50_ms"], lat["p95_ms"],
                        lat["p99_ms"], error_rate, s.passed])
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ordered = sorted(steps, key=lambda s: s.clients)
    clients = [s.clients for s in ordered]
    fig, ax = plt.subplots(figsize=(7, 4))
    for key, style in (("p50_ms", "o-"), ("p95_ms", "s-"), ("p99_ms", "^-")):
        ax.plot(clients, [s.summary["latency_all"][key] or float("nan") for s in ordered], style, label=key[:3])
    ax.axhline(p99_bound_ms, color="red", linestyle="--", label=f"bound {p99_bound_ms:g} ms")
    ax.axvline(best, color="green", linestyle=":", label=f"capacity {best} clients")
    ax.set_xlabel("clients")
    ax.set_ylabel("latency (ms)")
    ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "ramp.png", dpi=110)
    plt.close(fig)
