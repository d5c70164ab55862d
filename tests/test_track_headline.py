"""`flextrack track` on a recording that leaves the view: the FINE-only figure beside the all-frames one, and
an error plot with gaps where nothing was scored (issue 31 item 4)."""

from __future__ import annotations

import json
import math

import numpy as np

from flextrack.geometry.camera import PinholeCamera
from flextrack.runners.plots import plot_error
from flextrack.runners.results import TrackRecord
from flextrack.runners.track_cli import fine_only


def _pose(z: float, dx: float = 0.0) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [dx, 0.0, z]
    return T


def _record() -> TrackRecord:
    """Frames: 3 FINE within 1 mm, 2 out of view (no ground truth), 2 WRONG_POSE 10 cm off."""
    record = TrackRecord(PinholeCamera.linemod(), np.array([[0.05, 0, 0], [0, 0.05, 0], [0, 0, 0.05], [0, 0, 0]]))
    frames = [("FINE", 0.001), ("FINE", 0.001), ("FINE", 0.001), ("FINE", None), ("FINE", None),
              ("WRONG_POSE", 0.1), ("WRONG_POSE", 0.1)]
    for i, (status, dx) in enumerate(frames):
        record.add(i, i * 50_000_000, status, _pose(0.5, dx or 0.0), None if dx is None else _pose(0.5))
    return record


def test_fine_only_scores_the_frames_the_tracker_called_fine():
    record = _record()
    fine = fine_only(record)
    assert fine["frames"] == 3 and math.isclose(fine["pos_mm"], 1.0)
    assert fine["proj_px"] < record.summarize().proj_px / 10  # the lost frames dominate the all-frames mean
    json.dumps(fine)  # goes into the summary file


def test_error_plot_has_gaps_where_nothing_was_scored(tmp_path, monkeypatch):
    import matplotlib.axes

    plotted = []
    original = matplotlib.axes.Axes.plot
    monkeypatch.setattr(matplotlib.axes.Axes, "plot",
                        lambda self, *a, **k: plotted.append((a, k)) or original(self, *a, **k))
    path = plot_error(_record(), tmp_path / "error.png")
    assert path.stat().st_size > 10_000
    px = next(np.asarray(a[1], float) for a, k in plotted if k.get("label") == "2D error")
    assert np.isnan(px[3:5]).all() and np.isfinite(px[[0, 1, 2, 5, 6]]).all()  # a gap, not a line across it


def test_a_track_run_parses_its_sequence_folder_once(tmp_path, monkeypatch, capsys):
    """Issue 31 item 10: the runner loads the folder and the oracles answer from that load (was three)."""
    from flextrack.cli import main
    from flextrack.formats import sequence as sequence_io
    from flextrack.testing.toy_sequence import write_orbit_sequence

    seq = write_orbit_sequence(tmp_path / "orbit", frames=30)
    loads = []
    original = sequence_io.load
    monkeypatch.setattr(sequence_io, "load", lambda root: loads.append(root) or original(root))
    assert main(["track", str(seq.root), "--backend", "noisy", "--no-plots", "--out", str(tmp_path / "o")]) == 0
    assert len(loads) == 1, loads


def test_the_first_refusal_is_kept_in_the_server_s_words():
    """Issue 31 item 3: when every answer fails, `track` prints the first refusal, not a guess."""
    from flextrack.runners.exchange import apply_answer
    from flextrack.v1 import pose_estimation_pb2 as pb

    class Tracker:
        def on_backend_response(self, *args):
            pass

    record = _record()
    for message in ("estimator 'x' has no sequence 'orbit'", "a later one"):
        apply_answer(Tracker(), 1, pb.EstimateResponse(status=pb.EstimateResponse.OBJECT_NOT_FOUND, message=message),
                     record)
    assert record.first_refusal == "OBJECT_NOT_FOUND: estimator 'x' has no sequence 'orbit'" and record.failures == 2
