"""The live runner, `flextrack track` and `flextrack demo` end to end (real server, real sleeps)."""

import json

import numpy as np
import pytest

from client_sdk import TrackerOptions
from client_sdk.network_model import NetworkOptions
from flextrack.cli import main
from flextrack.formats import sequence as sequence_io
from flextrack.runners import session
from flextrack.runners.backends import oracle_registry
from flextrack.runners.live import LiveOptions, run_live
from flextrack.runners.results import RowStore, TrackRecord
from flextrack.simulator.generate import generate_sequence
from service.server import BackgroundServer


@pytest.fixture(scope="module")
def short_seq(tmp_path_factory):
    root = tmp_path_factory.mktemp("live") / "circular_medium"
    return sequence_io.load(generate_sequence("circular", "medium", root, duration_s=2.5, fps=60.0, seed=2,
                                              imu_profile="ideal"))


def test_live_run_through_the_sleeping_interceptor(short_seq):
    seen = []
    with BackgroundServer(oracle_registry([short_seq.root]), grace_s=0.0) as server:
        record = run_live(short_seq, server.address, session.model_vertices(short_seq), TrackerOptions(),
                          LiveOptions(network=NetworkOptions(seed=1), speed=2.0, keep_rows=16), progress=seen.append,
                          progress_every_s=0.1)
    # nothing grows with the frames unless asked: no error dynamics, at most 2 x keep_rows rows in memory
    assert record.error_dynamics is None and len(record.rows.recent()) < 32 < len(record.rows)
    summary = record.summarize()
    assert summary.frames == len(short_seq.frame_ids)
    assert summary.requests >= 10 and summary.responses >= summary.requests - 2  # the last may be in flight
    assert summary.failures == 0
    assert summary.proj_px < 0.5, summary
    assert seen and seen[-1].t_s == pytest.approx(seen[-1].total_s)


def test_a_record_with_its_older_rows_on_disk_scores_and_writes_the_same(short_seq, tmp_path):
    rng = np.random.default_rng(0)
    vertices = session.model_vertices(short_seq)
    records = [TrackRecord(short_seq.camera, vertices), TrackRecord(short_seq.camera, vertices, RowStore(keep=7))]
    T_gt = np.eye(4)
    T_gt[2, 3] = 0.6
    for i in range(100):
        T = T_gt.copy()
        T[:3, 3] += rng.normal(0, 1e-3, 3)
        status = "FINE" if i % 3 else "LOST"
        for record in records:
            record.add(i, 1_000_000 * i, status, None if i % 17 == 0 else T, None if i % 13 == 0 else T_gt,
                       np.eye(6) * 1e-6)
            if i == 50:
                record.last_scored()  # a progress line in the middle of the run
    memory, disk = records
    assert len(disk.rows.recent()) < 14 and len(disk.rows) == 100 and disk.rows[3].frame_id == 3
    assert disk.rows[-1].frame_id == 99 and [r.frame_id for r in disk.rows] == list(range(100))
    assert repr(disk.summarize()) == repr(memory.summarize())  # repr: nan == nan
    assert repr([(r.proj_px, r.jitter_px, r.nees) for r in disk.scored()]) == \
        repr([(r.proj_px, r.jitter_px, r.nees) for r in memory.scored()])
    memory.write(tmp_path / "memory")
    disk.write(tmp_path / "disk")
    for name in ("track_frames.csv", "track_estimate.tum", "track_summary.json"):
        assert (tmp_path / "disk" / name).read_text() == (tmp_path / "memory" / name).read_text()


def test_live_run_without_a_server_fails_cleanly(short_seq):
    with pytest.raises(ConnectionError, match="no backend answered"):
        run_live(short_seq, "127.0.0.1:1", session.model_vertices(short_seq),
                 options=LiveOptions(connect_timeout_s=0.3))


def test_track_cli_writes_results_and_rejects_bad_input(short_seq, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["track", str(short_seq.root), "--out", str(out), "--backend", "noisy", "--no-plots"]) == 0
    summary = json.loads((out / f"{short_seq.name}_noisy_summary.json").read_text())
    assert summary["frames"] == len(short_seq.frame_ids) and summary["proj_px"] < 10
    prov = summary["provenance"]  # flextrack.provenance: the options, seed included, commit, dirty, host, date
    assert prov["options"]["backend"] == "noisy" and "seed" in prov["options"] and {"commit", "dirty", "host", "date"} <= set(prov)
    assert (out / f"{short_seq.name}_noisy_estimate.tum").stat().st_size > 0
    assert "| run |" in capsys.readouterr().out
    assert main(["track", str(tmp_path / "missing"), "--out", str(out)]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["track", str(short_seq.root), "--out", str(out), "--backend", "nope", "--no-plots"]) == 2
    assert "unknown estimator" in capsys.readouterr().err
    tuned = ["track", str(short_seq.root), "--out", str(tmp_path / "tuned"), "--backend", "noisy", "--no-plots",
             "--tracker", "paper", "--set", "gravity_follow=0.5", "--set", "pia=false"]
    assert main(tuned) == 0
    capsys.readouterr()
    filtered = ["track", str(short_seq.root), "--out", str(tmp_path / "filtered"), "--backend", "noisy", "--no-plots",
                "--set", "filter.time_offset_std_s=0", "--set", "filter.max_rejections=5"]
    assert main(filtered) == 0
    assert "| run |" in capsys.readouterr().out
    assert main(["track", str(short_seq.root), "--out", str(out), "--set", "filter.warp=1", "--no-plots"]) == 2
    assert "unknown filter option 'warp'; one of " in capsys.readouterr().err
    assert main(["track", str(short_seq.root), "--out", str(out), "--set", "warp=9", "--no-plots"]) == 2
    assert "unknown option 'warp'; one of " in capsys.readouterr().err
    assert main(["track", str(short_seq.root), "--out", str(out), "--set", "pose_gain=2", "--no-plots"]) == 2
    assert "pose_gain" in capsys.readouterr().err
    # the simulator declares its extrinsic and frame times exact: the floor is set from that, not from --set
    assert main(["track", str(short_seq.root), "--out", str(out), "--set", "filter.answer_floor_translation_m=0.001",
                 "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert "declares what it cannot know exactly (sequence.yaml timing_extrinsic_std)" in err and err.count("\n") == 1


def test_demo_runs_live_end_to_end(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--duration", "3", "--no-replay"]) == 0
    text = capsys.readouterr().out
    assert "tracking LIVE" in text and "| live, noisy |" in text
    assert (out / "live_noisy_error.png").stat().st_size > 0
    assert (out / "live_noisy_trajectory.png").stat().st_size > 0
