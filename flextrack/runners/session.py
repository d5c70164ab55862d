"""One tracking run, end to end: the backend it needs (embedded server, external server or
in-process), the replay or live runner, and the outputs. Used by `flextrack track`, the demo and
the experiments.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field, replace
from functools import lru_cache
from pathlib import Path

import numpy as np

from client_sdk import TrackerOptions
from client_sdk.network_model import NetworkOptions
from client_sdk.slowdown import PIXEL2_FACTOR
from estimators.gt_oracle import GtOracleEstimator
from estimators.objects import load_object, load_object_folders
from estimators.registry import EstimatorRegistry
from flextrack.formats.sequence import Sequence
from flextrack.runners import plots
from flextrack.runners.backends import GrpcBackend, InProcessBackend, oracle_registry
from flextrack.runners.live import LiveOptions, Progress, run_live
from flextrack.runners.payload import RenderedJpegs
from flextrack.runners.replay import ReplayOptions, replay
from flextrack.runners.results import TrackRecord


@dataclass(frozen=True)
class RunSpec:
    backend: str = "gt"  # estimator name
    network: NetworkOptions = field(default_factory=NetworkOptions)
    slowdown: float = PIXEL2_FACTOR
    backend_compute_ms: float = 0.0
    seed: int = 0  # Noisy-backend seed (the network seed is in `network`)
    live: bool = False
    speed: float = 1.0
    in_process: bool = False
    config: Path | None = None  # estimator config instead of the oracles
    objects: tuple[Path, ...] = ()  # BOP models folders the config's region estimators serve too (--objects)
    server: str | None = None  # external server address
    frames: bool = False  # send rendered frames (image estimators) instead of the stand-in JPEG


def at_fps(seq: Sequence, fps: float) -> Sequence:
    """The sequence with the frames nearest to a 1/fps grid (a camera at a lower frame rate)."""
    if fps <= 0:
        raise ValueError(f"fps must be > 0, got {fps}")
    times = seq.frame_times_ns
    grid = np.arange(times[0], times[-1] + 1, 1e9 / fps)
    after = np.clip(np.searchsorted(times, grid), 1, len(times) - 1)
    nearer_before = grid - times[after - 1] <= times[after] - grid
    idx = np.unique(np.where(nearer_before, after - 1, after))
    return replace(seq, frame_ids=seq.frame_ids[idx], frame_times_ns=times[idx])


def registry_for(seq: Sequence, spec: RunSpec) -> EstimatorRegistry:
    """The estimators a run serves: the oracles, or the config's with its oracles given `seq`. `seq` as loaded
    (its whole ground truth: the oracles answer from it, without parsing the folder again)."""
    if spec.config is None:
        return oracle_registry([seq], noise_seed=spec.seed)
    models = load_object_folders(spec.objects)
    registry = EstimatorRegistry.from_config(spec.config, models)
    registry.prepare([m.object_id for m in models])  # as `flextrack serve --objects`: no frame waits for one
    for estimator in registry:
        if isinstance(estimator, GtOracleEstimator):
            estimator.add_sequence(seq, seq.name)
    return registry


def model_vertices(seq: Sequence) -> np.ndarray:
    return _vertices(seq.object_id, str(Path(seq.model_path).resolve()))


@lru_cache(maxsize=8)
def _vertices(object_id: str, model_path: str) -> np.ndarray:
    return load_object(object_id, model_path).vertices


def track(seq: Sequence, tracker_options: TrackerOptions, spec: RunSpec,
          progress: Callable[[Progress], None] | None = None, registry: EstimatorRegistry | None = None) -> TrackRecord:
    """Track `seq` as `spec` says; `registry` reuses an already built one (experiments)."""
    from service.server import BackgroundServer  # the server extra; imported only when a run needs it

    vertices = model_vertices(seq)
    if spec.server is None:
        registry = registry or registry_for(seq, spec)
        if spec.backend not in registry.names():
            raise ValueError(f"unknown estimator '{spec.backend}'; available: {registry.names()} "
                             "(pass --config FILE for an estimator config that lists it)")
    with ExitStack() as stack:
        frame_jpeg = None
        if spec.frames:
            frame_jpeg = RenderedJpegs(seq)
            stack.callback(frame_jpeg.close)
        address = spec.server
        if spec.in_process and not spec.live:
            backend = InProcessBackend(registry, spec.network)
        else:
            if address is None:
                server = stack.enter_context(BackgroundServer(registry))
                address = server.address
            if spec.live:
                options = LiveOptions(network=spec.network, slowdown=spec.slowdown, estimator=spec.backend,
                                      speed=spec.speed)
                return run_live(seq, address, vertices, tracker_options, options, progress, frame_jpeg=frame_jpeg)
            backend = GrpcBackend(address, spec.network)
            stack.callback(backend.close)
        options = ReplayOptions(network=spec.network, slowdown=spec.slowdown,
                                backend_compute_ms=spec.backend_compute_ms, estimator=spec.backend)
        return replay(seq, backend, vertices, tracker_options, options, frame_jpeg=frame_jpeg, progress=progress)


def print_progress(p: Progress, stream=sys.stderr) -> None:
    """One self-overwriting status line."""
    row = p.record.last_scored()  # not scored(): that reads a live record's rows back from disk
    last = row.proj_px if row is not None else float("nan")
    line = (f"\r  t {p.t_s:5.1f}/{p.total_s:.1f} s  frames {len(p.record.rows):5d}  {p.status:<14}  "
            f"2D err {last:6.2f} px  requests {p.record.requests:4d}  answers {p.record.responses:4d}  "
            f"{'connected' if p.connected else 'RECONNECTING'}")
    stream.write(line)
    stream.flush()
    if p.t_s >= p.total_s:
        stream.write("\n")


def write_plots(record: TrackRecord, out_dir: str | Path, name: str) -> list[Path]:
    out = Path(out_dir)
    return [plots.plot_error(record, out / f"{name}_error.png", f"{name}: 2D projection error"),
            plots.plot_trajectory(record, out / f"{name}_trajectory.png", name)]
