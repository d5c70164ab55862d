"""Frontend timing: PIM (one frame: propagate to it, PIA check, request decision), PRM (one backend
response) and PPM (one IMU sample), per call, for both trackers on the same replay: the filter
(the default) and the paper's reset, alternating run by run so that the machine's load falls on
both alike. Raw and stretched by the Pixel 2 factor, beside the paper's 0.35 ms and 0.86 ms (after
its stretch) and the filter's budget (issue 16: 20 us per IMU sample, 400 us per answer, raw).

A benchmark, not a test: the figures depend on the machine and its load; compare the two trackers
within one run.
"""

from __future__ import annotations

import platform
import time
from pathlib import Path

import numpy as np

from client_sdk.network_model import NetworkOptions
from client_sdk.options import preset
from client_sdk.slowdown import PIXEL2_FACTOR
from flextrack.experiments import common, paper
from flextrack.runners.replay import ReplayOptions, replay
from flextrack.runners.session import model_vertices

HEADER = ["tracker", "operation", "median_us", "p99_us", "stretched_median_us", "paper_ms", "budget_us", "calls"]
OPERATIONS = {"pim": "add_frame", "prm": "on_backend_response", "ppm": "add_imu"}
TRACKERS = ("filter", "paper")
BUDGET_US = {("filter", "ppm"): 20.0, ("filter", "prm"): 400.0}  # issue 16, raw medians


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
    samples = {(tracker, op): [] for tracker in TRACKERS for op in OPERATIONS}
    spec = common.SimSpec("translational", "medium", 120, seed, duration_s)
    with common.OracleBackend(noise_seed=seed, in_process=in_process) as oracle, \
            common.progress(repeats * len(TRACKERS), "timing") as bar:
        seq = common.simulated(cache, spec)
        oracle.learn(seq)
        for _ in range(repeats):
            for tracker in TRACKERS:
                timed: list[TimedTracker] = []

                def wrap(core, timed=timed):
                    timed.append(TimedTracker(core))
                    return timed[-1]

                options = ReplayOptions(network=NetworkOptions(seed=seed), estimator="noisy",
                                        record_error_dynamics=False)
                with oracle.client(options) as backend:
                    replay(seq, backend, model_vertices(seq), preset(tracker), options, wrap=wrap)
                for op in OPERATIONS:
                    samples[tracker, op] += timed[0].samples[op]
                bar.update()
    rows = []
    for (tracker, op), ns in samples.items():
        us = np.array(ns) / 1e3
        med = float(np.median(us))
        rows.append([tracker, op, med, float(np.percentile(us, 99)), med * PIXEL2_FACTOR,
                     paper.TIMING_MS.get(op, ""), BUDGET_US.get((tracker, op), ""), len(us)])
    common.write_csv(out / "timing.csv", HEADER, rows)
    (out / "timing.md").write_text(report(rows, spec, repeats))
    return rows


def report(rows: list[list], spec, repeats: int) -> str:
    def dash(v):
        return "-" if v == "" else v

    table = [[r[0], r[1], r[2], r[3], r[4], dash(r[5]), dash(r[6]), r[7]] for r in rows]
    return "\n".join([
        "# Frontend timing (per call)", "",
        (f"{spec.motion} {spec.level} at {spec.fps:g} FPS, {spec.duration_s:g} s, replayed {repeats}x per tracker "
         f"(alternating) with the Noisy backend; machine: {platform.machine()} {platform.processor() or ''}, Python "
         f"{platform.python_version()}. Stretched = raw x {PIXEL2_FACTOR:.2f} (the paper's Pixel 2 emulation); the "
         "paper reports stretched figures; the budget is the filter's, on raw medians."),
        "",
        common.markdown_table(["tracker", "operation", "median us", "p99 us", "stretched median us", "paper ms",
                               "budget us", "calls"], table),
        "", OPERATION_NOTE,
    ]) + "\n"


OPERATION_NOTE = ("pim = `add_frame` (the pose at the frame, for the filter its covariance and projected "
                  "uncertainty, the PIA, the request decision); prm = `on_backend_response` (filter: the update at "
                  "the capture time and the state and covariance re-propagated over the round trip; paper: the "
                  "reset, BSCM and the re-propagation); ppm = `add_imu` (one propagation step; the filter's "
                  "with its 19x19 covariance).")
