"""One's own recording (issue 19, points 1-9): a small EuRoC-layout recording with no still window, the object
placed (by option) where the camera does not look at the start; convert-euroc, track and experiment euroc on it
say what they scored and why not, take the same tracker options, key their cache by content, label by data."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from flextrack.cli import main
from flextrack.formats.sequence import load
from flextrack.runners.exchange import frame_latency_ns
from flextrack.runners.scoring import in_view
from flextrack.simulator.euroc_convert import convert_euroc
from flextrack.testing.euroc_recording import IMU_NAME, write_euroc_recording


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """(EuRoC folder, an object position out of view at the start and in view later, its frames in view)."""
    base = tmp_path_factory.mktemp("own")
    data = write_euroc_recording(base / "my_walk", base / "work", duration_s=10)
    seq = load(convert_euroc(data, base / "probe"))  # auto placement: in view from the start
    T_WC = np.stack([seq.T_WO @ np.linalg.inv(seq.gt_T_CO[int(i)]) for i in seq.frame_ids])
    centre = np.array(seq.meta["placement"]["centre_W"])
    start = -(T_WC[0, :2, 3] - centre[:2]) / np.linalg.norm(T_WC[0, :2, 3] - centre[:2])
    for offset in (0.8, -0.8, 1.0, -1.0):  # beside the start's line of sight, where the camera turns later
        position = centre + offset * np.array([-start[1], start[0], 0.0])
        seen = np.array([in_view(_translation(np.linalg.inv(T) @ np.append(position, 1.0)), seq.camera)
                         for T in T_WC])
        if not seen[:10].any() and seen.sum() >= 20:
            return data, ",".join(f"{x:.4f}" for x in position)
    raise AssertionError("no position out of view at the start and in view later")


def _translation(p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = p[:3]
    return T


@pytest.fixture(scope="module")
def sequence(recording, tmp_path_factory):
    data, position = recording
    out = tmp_path_factory.mktemp("seq") / "walk"
    assert main(["convert-euroc", "--euroc", str(data), "--out", str(out), f"--object-position={position}"]) == 0
    return out


def test_convert_euroc_reports_rate_imu_and_placement(recording, sequence, capsys):
    data, position = recording
    assert main(["convert-euroc", "--euroc", str(data), "--out", str(sequence.parent / "again"), "--no-plots",
                 f"--object-position={position}", "--frame-latency", "20"]) == 0
    out = capsys.readouterr().out
    assert "at 30 FPS" in out and IMU_NAME in out and "object (given) at" in out  # the camera file's 30 Hz
    assert (sequence / "plots" / "trajectory.png").stat().st_size > 10_000  # the placement drawn
    seq = load(sequence)
    assert seq.meta["placement"]["how"] == "given" and seq.meta["converter"]["imu"] == IMU_NAME
    # a recording declares no frame latency unless told: a phone's 50 ms; told, its own
    assert frame_latency_ns(seq) == 50_000_000 and frame_latency_ns(load(sequence.parent / "again")) == 20_000_000
    with pytest.raises(SystemExit):
        main(["convert-euroc", "--help"])
    help_text = capsys.readouterr().out
    assert "20 Hz" not in help_text and "rate_hz" in help_text


def test_track_scores_only_frames_in_view_and_says_how_many_it_skipped(sequence, tmp_path, capsys):
    seq = load(sequence)
    out_of_view = sum(not in_view(T, seq.camera) for T in seq.gt_T_CO.values())
    assert out_of_view >= 10
    assert main(["track", str(sequence), "--backend", "noisy", "--no-plots", "--out", str(tmp_path)]) == 0
    printed = capsys.readouterr().out
    assert f"not scored: {out_of_view} out of view" in printed and "worst FINE frame" in printed
    accounting = json.loads((tmp_path / f"{sequence.name}_noisy_summary.json").read_text())["accounting"]
    assert accounting["out_of_view"] == out_of_view and accounting["scored"] > 0


def test_track_that_scores_nothing_exits_non_zero_with_the_reason(sequence, tmp_path, capsys):
    # the paper's method waits for a still window, which this recording has not
    rc = main(["track", str(sequence), "--backend", "noisy", "--tracker", "paper", "--no-plots", "--out", str(tmp_path)])
    assert rc == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "never initialised" in err and "still" in err
    assert (tmp_path / f"{sequence.name}_noisy_summary.json").exists()  # its outputs are written all the same


def test_experiment_euroc_on_own_data(recording, tmp_path, capsys):
    data, position = recording
    argv = ["experiment", "euroc", "--data", str(data), "--in-process", "--out", str(tmp_path),
            f"--object-position={position}", "--fps", "30", "--set", "filter.gate_chi2=30"]
    assert main(argv) == 0
    report = (tmp_path / "euroc.md").read_text()
    assert "my_walk" in report and IMU_NAME in report and "V1_02" not in report and "ADIS16448" not in report
    assert "| out of view | initialising | lost |" in report and "worst FINE" in report
    assert "`full` scored nothing: the tracker never initialised" in report  # no still window for the paper's
    assert "| preset filter filter.gate_chi2=30 |" in report  # the same tracker options as track's
    assert "at 30 FPS" in report
    assert list((tmp_path / "sequences").glob("*/plots/trajectory.png"))  # the placement, drawn
    # the cache: the same data and options reuse the conversion; another recording in the same OUT does not
    assert main(argv) == 0
    assert len(list((tmp_path / "sequences").iterdir())) == 1
    other = tmp_path.parent / "shorter"
    shutil.copytree(data, other)
    lines = (other / "imu0.csv").read_text().splitlines()
    (other / "imu0.csv").write_text("\n".join(lines[:1] + lines[1 + len(lines) // 5:]) + "\n")  # starts later
    assert main([*argv[:3], str(other), *argv[4:]]) == 0
    assert len(list((tmp_path / "sequences").iterdir())) == 2
    assert (tmp_path / "euroc.md").read_text().split("frames at")[0] != report.split("frames at")[0]


def test_experiment_euroc_that_scores_nothing_exits_non_zero(recording, tmp_path, capsys):
    data, _ = recording
    rc = main(["experiment", "euroc", "--data", str(data), "--in-process", "--out", str(tmp_path),
               "--object-position=50,50,50"])
    assert rc == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("flextrack")]
    assert len(err) == 1 and "nothing scored" in err[0] and "in view in none" in err[0]


def test_the_ablation_runs_on_a_hand_held_recording(recording, tmp_path):
    """`experiment ablation --data`: the paper's variants on a recording without a still window start all the
    same (init_require_still lifted), scored on the FINE frames in view as experiment euroc scores them."""
    import csv

    data, _ = recording
    assert main(["experiment", "ablation", "--data", str(data), "--in-process", "--out", str(tmp_path)]) == 0
    rows = list(csv.DictReader((tmp_path / "ablation.csv").read_text().splitlines()))
    assert {r["motion"] for r in rows} == {"my_walk"} and len(rows) == 12
    full = {r["backend"]: float(r["proj_px"]) for r in rows if r["variant"] == "full"}
    assert all(np.isfinite(v) for v in full.values())  # it started while moving
    assert "init_require_still=False" in (tmp_path / "ablation.md").read_text()
    assert json.loads((tmp_path / "ablation.json").read_text())["provenance"]["options"]["data"] == str(data)
