"""What every experiment shares: simulated sequences (cached by their settings), a backend server
whose oracles learn sequences as they are generated, grids of cells run in parallel processes,
CSV/Markdown writing and a progress bar.
"""

from __future__ import annotations

import csv
import multiprocessing
import os
from collections.abc import Callable, Iterator
from concurrent.futures import ProcessPoolExecutor, as_completed
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Self

from tqdm import tqdm

from client_sdk import TrackerOptions
from client_sdk.options import preset
from estimators.gt_oracle import GtOracleEstimator
from estimators.registry import EstimatorRegistry
from flextrack.formats import sequence as sequence_io
from flextrack.formats.sequence import Sequence
from flextrack.runners.backends import NOISY_R_DEG, NOISY_T_M, GrpcBackend, InProcessBackend
from flextrack.runners.exchange import SIMULATOR_DECLARATIONS
from flextrack.runners.replay import ReplayOptions, replay
from flextrack.runners.results import TrackRecord
from flextrack.runners.session import model_vertices

# The tracker as the paper describes it and the filter (client_sdk.options.preset explains both).
PAPER_FAITHFUL = preset("paper")
FILTER = preset("filter")
TRACKER_VARIANTS = {"filter": FILTER, "paper": PAPER_FAITHFUL}
VARIANT_TITLES = {
    "filter": "filter (the error-state Kalman filter, the same options for every backend)",
    "paper": "paper-faithful (each backend pose resets the state; BSCM with the damped default gains)",
}


@dataclass(frozen=True)
class SimSpec:
    motion: str
    level: str
    fps: float
    seed: int = 0
    duration_s: float = 30.0
    imu: str = "pixel2"

    @property
    def name(self) -> str:
        return f"{self.motion}_{self.level}_{self.fps:g}fps_{self.duration_s:g}s_{self.imu}_seed{self.seed}"


@dataclass(frozen=True)
class GridCell:
    """One (seed, program, frame rate) of a grid experiment, as a worker process of `run_cells` gets it."""

    out: Path
    seed: int
    motion: str
    level: str
    fps: float
    duration_s: float
    in_process: bool

    def spec(self, imu: str = "pixel2") -> SimSpec:
        return SimSpec(self.motion, self.level, self.fps, self.seed, self.duration_s, imu)


def simulated(cache: Path, spec: SimSpec) -> Sequence:
    """The sequence of `spec`, generated into `cache` the first time (no rendering: oracles need no pixels), and
    again when the cached one predates what the generator now declares for the tracker (`SIMULATOR_DECLARATIONS`):
    without it the tracker would take the simulator's exact IMU and timing for a phone's."""
    from flextrack.simulator.generate import generate_sequence

    root = cache / spec.name
    cached = sequence_io.load(root) if (root / "rig.yaml").is_file() else None
    if cached is not None and all(key in cached.meta for key in SIMULATOR_DECLARATIONS):
        return cached
    generate_sequence(spec.motion, spec.level, root, duration_s=spec.duration_s, fps=spec.fps, seed=spec.seed,
                      imu_profile=spec.imu)
    return sequence_io.load(root)


class OracleBackend:
    """"gt" and "noisy" oracles (and any `extra` ones) behind a real gRPC server (or in-process), learning
    sequences on the way."""

    def __init__(self, noise_seed: int, in_process: bool = False, extra: tuple[GtOracleEstimator, ...] = ()):
        self.gt = GtOracleEstimator("gt")
        self.noisy = GtOracleEstimator("noisy", noise_t_m=NOISY_T_M, noise_r_deg=NOISY_R_DEG, seed=noise_seed)
        self.oracles = (self.gt, self.noisy, *extra)
        self.registry = EstimatorRegistry(self.oracles, default="gt")
        self.in_process = in_process
        self._server = None

    def __enter__(self) -> Self:
        if not self.in_process:
            from service.server import BackgroundServer

            self._server = BackgroundServer(self.registry).start()
        return self

    def __exit__(self, *exc) -> None:
        if self._server is not None:
            self._server.stop()

    def learn(self, seq: Sequence) -> None:
        for oracle in self.oracles:
            if seq.name not in oracle.sequences:
                oracle.add_sequence(seq.root, seq.name)

    @contextmanager
    def client(self, options: ReplayOptions) -> Iterator:
        if self._server is None:
            yield InProcessBackend(self.registry, options.network)
            return
        backend = GrpcBackend(self._server.address, options.network)
        try:
            yield backend
        finally:
            backend.close()

    def run(self, seq: Sequence, tracker_options: TrackerOptions, options: ReplayOptions) -> TrackRecord:
        self.learn(seq)
        with self.client(options) as backend:
            return replay(seq, backend, model_vertices(seq), tracker_options, options)


def write_csv(path: Path, header: list[str], rows: list[list]) -> Path:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        for row in rows:
            w.writerow([f"{v:.4f}" if isinstance(v, float) else v for v in row])
    return path


def markdown_table(header: list[str], rows: list[list]) -> str:
    def cell(v):
        return f"{v:.2f}" if isinstance(v, float) else str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def progress(total: int, desc: str, unit: str = "run") -> tqdm:
    return tqdm(total=total, desc=desc, unit=unit, dynamic_ncols=True, leave=True)


def default_jobs() -> int:
    """One process per CPU this process may use."""
    return max(1, len(os.sched_getaffinity(0)))


def run_cells(worker: Callable, tasks: list, jobs: int, desc: str, describe: Callable[[object], str],
              cost: Callable[[object], float] = lambda task: 0.0) -> list:
    """`worker(task)` for every task, results in the tasks' order, with a progress bar (`describe(result)` its
    postfix). With jobs > 1 the tasks run in that many spawned processes (each cell starts its own backend
    there: no gRPC state crosses a fork), the costliest first so that none is left alone at the end. A
    cell's result depends only on its task (the oracles draw their noise from (seed, sequence, time), the
    network from its seed), so it is the same for any `jobs`."""
    results: list = [None] * len(tasks)
    with progress(len(tasks), desc, unit="cell") as bar:
        def done(i: int, result) -> None:
            results[i] = result
            bar.set_postfix_str(describe(result))
            bar.update()

        if jobs <= 1 or len(tasks) <= 1:
            for i, task in enumerate(tasks):
                done(i, worker(task))
            return results
        with ProcessPoolExecutor(max_workers=min(jobs, len(tasks)),
                                 mp_context=multiprocessing.get_context("spawn")) as pool:
            order = sorted(range(len(tasks)), key=lambda i: -cost(tasks[i]))
            futures = {pool.submit(worker, tasks[i]): i for i in order}
            try:
                for future in as_completed(futures):
                    done(futures[future], future.result())
            except BaseException:
                pool.shutdown(cancel_futures=True)
                raise
    return results
