"""Frontend timing: PIM (one frame: propagate to it, PIA check, request decision), PRM (one backend
response: reset, BSCM, re-propagation) and PPM (one IMU sample), per call, raw and stretched by
the Pixel 2 factor, beside the paper's 0.35 ms and 0.86 ms (after its stretch).

A benchmark, not a test: the figures depend on the machine and its load.
"""

from __future__ import annotations

import platform
import time
from pathlib import Path

import numpy as np

from client_sdk import TrackerOptions
from client_sdk.network_model import NetworkOptions
from client_sdk.slowdown import PIXEL2_FACTOR
from flextrack.experiments import common, paper
from flextrack.runners.replay import ReplayOptions, replay
from flextrack.runners.session import model_vertices

HEADER = ["operation", "median_us", "p99_us", "stretched_median_us", "paper_ms"]
OPERATIONS = {"pim": "add_frame", "prm": "on_backend_response", "ppm": "add_imu"}


class TimedTracker:
    """Proxy that records the duration of each call to the timed methods (ns, perf_counter_ns)."""

    def __init__(self, tracker):
        self._tracker = tracker
        self.samples: dict[str, list[int]] = {op: [] for op in OPERATIONS}
        for op, method in OPERATIONS.items():
            setattr(self, method, self._timed(op, getattr(tracker, method)))

    def _timed(self, op, fn):
        samples = self.samples[op]

        def call(*args, **kwargs):
            start = time.perf_counter_ns()
            result = fn(*args, **kwargs)
            samples.append(time.perf_counter_ns() - start)
            return result
        return call

    def __getattr__(self, name):
        return getattr(self._tracker, name)


def run(out: Path, seed: int = 0, duration_s: float = 30.0, repeats: int = 3, in_process: bool = True) -> list[list]:
    cache = out / "sequences"
    samples: dict[str, list[int]] = {op: [] for op in OPERATIONS}
    spec = common.SimSpec("translational", "medium", 120, seed, duration_s)
    with common.OracleBackend(noise_seed=seed, in_process=in_process) as oracle, \
            common.progress(repeats, "timing") as bar:
        seq = common.simulated(cache, spec)
        oracle.learn(seq)
        for _ in range(repeats):
            timed: list[TimedTracker] = []

            def wrap(tracker, timed=timed):
                timed.append(TimedTracker(tracker))
                return timed[-1]

            options = ReplayOptions(network=NetworkOptions(seed=seed), estimator="noisy", record_error_dynamics=False)
            with oracle.client(options) as backend:
                replay(seq, backend, model_vertices(seq), TrackerOptions(), options, wrap=wrap)
            for op in OPERATIONS:
                samples[op] += timed[0].samples[op]
            bar.update()
    rows = []
    for op in OPERATIONS:
        us = np.array(samples[op]) / 1e3
        med = float(np.median(us))
        rows.append([op, med, float(np.percentile(us, 99)), med * PIXEL2_FACTOR, paper.TIMING_MS.get(op, "")])
    common.write_csv(out / "timing.csv", HEADER, rows)
    counts = {op: len(v) for op, v in samples.items()}
    (out / "timing.md").write_text(report(rows, counts, spec, repeats))
    return rows


def report(rows: list[list], counts: dict, spec, repeats: int) -> str:
    table = [[r[0], r[1], r[2], r[3], r[4] if r[4] != "" else "-", counts[r[0]]] for r in rows]
    return "\n".join([
        "# Frontend timing (per call)", "",
        (f"{spec.motion} {spec.level} at {spec.fps:g} FPS, {spec.duration_s:g} s, replayed {repeats}x with the Noisy "
        f"backend; machine: {platform.machine()} {platform.processor() or ''}, Python {platform.python_version()}. "
        f"Stretched = raw x {PIXEL2_FACTOR:.2f} (the paper's Pixel 2 emulation); the paper reports stretched figures."),
        "",
        common.markdown_table(["operation", "median us", "p99 us", "stretched median us", "paper ms", "calls"], table),
        "", ("pim = `Tracker.add_frame` (pose at the frame, PIA, request decision); prm = `on_backend_response` "
        "(state reset, BSCM, re-propagation of the buffered IMU); ppm = `add_imu` (one propagation step)."),
    ]) + "\n"
