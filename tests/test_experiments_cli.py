"""`flextrack experiment` end to end on short sequences: the CSV columns the issue fixes, reports, plots."""

import csv
import json

import numpy as np
import pytest

from flextrack.cli import main


def _csv(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_table2_on_short_sequences_writes_the_agreed_csv(tmp_path, capsys):
    out = tmp_path / "t2"
    assert main(["experiment", "table2", "--out", str(out), "--duration", "3", "--fps", "30", "--in-process",
                 "--jobs", "1"]) == 0
    rows = _csv(out / "table2.csv")
    assert list(rows[0]) == ["motion", "level", "fps", "backend", "seed", "pos_mm", "ori_deg", "proj_px",
                             "paper_pos_mm", "paper_ori_deg", "paper_proj_px", "jitter_px", "nees_mean", "nees_lo",
                             "nees_hi", "worst_fine_px"]
    assert len(rows) == 6 * 2  # six programs x two backends at one frame rate
    assert {(r["motion"], r["backend"]) for r in rows} == {(m, b) for m in ("translational", "circular")
                                                           for b in ("gt", "noisy")}
    gt = [float(r["proj_px"]) for r in rows if r["backend"] == "gt"]
    assert all(0 <= px < 50 for px in gt)
    assert float(next(r for r in rows if r["motion"] == "circular" and r["level"] == "hard"
                      and r["backend"] == "noisy")["paper_proj_px"]) == 2.01
    assert (out / "table2.png").stat().st_size > 0
    assert "Table 2 rerun" in (out / "table2.md").read_text()
    record = json.loads((out / "table2.json").read_text())  # provenance of the run (flextrack.provenance)
    assert record["provenance"]["options"]["seed_list"] == [0] and record["provenance"]["options"]["duration"] == 3
    assert {"commit", "dirty", "host", "date"} <= set(record["provenance"])
    assert {"table2.csv", "table2_paper.csv", "table2.md"} <= set(record["files"])
    paper_rows = _csv(out / "table2_paper.csv")  # the paper-faithful tracker, same columns
    assert list(paper_rows[0]) == list(rows[0]) and len(paper_rows) == len(rows)
    tum = out / "trajectories" / "filter_circular_medium_30fps_gt_estimate.tum"
    assert tum.read_text().startswith("# timestamp tx ty tz qx qy qz qw")
    assert "Table 2 rerun" in capsys.readouterr().out


def test_table2_cells_in_parallel_processes_give_the_same_rows(tmp_path):
    from flextrack.experiments import table2

    grid = {"duration_s": 2.0, "fps_list": (30,), "motions": ("translational",), "levels": ("easy", "hard")}
    alone = table2.run(tmp_path / "one", [0], jobs=1, **grid)
    parallel = table2.run(tmp_path / "two", [0], jobs=2, **grid)  # spawned workers, a gRPC server each
    assert len(alone) == 4 and parallel == alone
    assert (tmp_path / "one" / "table2_paper.csv").read_text() == (tmp_path / "two" / "table2_paper.csv").read_text()


def test_timing_writes_the_agreed_csv(tmp_path):
    out = tmp_path / "timing"
    assert main(["experiment", "timing", "--out", str(out), "--duration", "3"]) == 0
    rows = _csv(out / "timing.csv")
    assert list(rows[0]) == ["tracker", "operation", "median_us", "p99_us", "stretched_median_us", "paper_ms",
                             "budget_us", "calls"]
    assert [(r["tracker"], r["operation"]) for r in rows] == [(t, op) for t in ("filter", "paper")
                                                              for op in ("pim", "prm", "ppm")]
    for r in rows:
        assert float(r["stretched_median_us"]) > float(r["median_us"]) > 0
    calls = {(r["tracker"], r["operation"]): int(r["calls"]) for r in rows}
    assert calls["filter", "ppm"] == calls["paper", "ppm"] > 0  # the same replay for both
    assert [float(r["budget_us"] or 0) for r in rows if r["tracker"] == "filter"] == [0, 400, 20]
    # the stored result renders (the figures themselves are the machine's: a benchmark, not asserted)
    from flextrack import report

    assert "filter's budget" in report.RENDERERS["timing"](out)


def test_bad_arguments_are_refused(tmp_path, capsys):
    assert main(["experiment", "euroc", "--out", str(tmp_path), "--data", str(tmp_path / "nope")]) == 2
    assert "not found" in capsys.readouterr().err


def test_ablation_writes_the_agreed_csv_and_the_sawtooth(tmp_path):
    out = tmp_path / "abl"
    assert main(["experiment", "ablation", "--out", str(out), "--duration", "3", "--in-process"]) == 0
    rows = _csv(out / "ablation.csv")
    assert list(rows[0]) == ["variant", "backend", "motion", "level", "fps", "proj_px", "jitter_px", "nees_mean",
                             "worst_fine_px"]
    variants = {"full", "bscm_pia_off", "imu_only", "filter", "filter_default_covariance", "filter_no_gravity_state"}
    assert {r["variant"] for r in rows} == variants and len(rows) == len(variants) * 2 * 6
    for name in ("ablation.png", "sawtooth.png", "ablation_over_time.png"):
        assert (out / name).stat().st_size > 0


def test_euroc_writes_the_agreed_csv(tmp_path):
    from flextrack.experiments.euroc import DEFAULT_DATA

    if not DEFAULT_DATA.is_dir():
        pytest.skip(f"EuRoC data not found at {DEFAULT_DATA} (see shared/data/SOURCES.md)")
    out = tmp_path / "euroc"
    assert main(["experiment", "euroc", "--out", str(out), "--in-process"]) == 0
    rows = _csv(out / "euroc.csv")
    assert list(rows[0]) == ["variant", "pos_mm", "ori_deg", "proj_px", "jitter_px", "nees_mean", "worst_fine_px",
                             "fine_share", "time_offset_ms", "time_offset_sigma_ms", "offset_xcorr_ms",
                             "set_aside_frames", "worst_set_aside_px"]
    assert all(0 < float(r["fine_share"]) <= 1 for r in rows) and abs(float(rows[0]["offset_xcorr_ms"])) < 2
    assert all(r["set_aside_frames"] == "0" for r in rows)  # the Vicon's truth never jumps where the IMU did not
    filter_row = rows[-1]
    assert abs(float(filter_row["time_offset_ms"])) < 10 and 0 < float(filter_row["time_offset_sigma_ms"]) < 20
    assert [r["variant"] for r in rows] == ["full", "bscm_off", "filter"]


def test_table2_with_the_pvnet_backend_renders_frames_and_reports_beside_the_oracle(tmp_path):
    pytest.importorskip("onnxruntime")
    from flextrack.experiments import table2_vision

    out = tmp_path / "t2v"
    rows = table2_vision.run(out, "pvnet", [0], duration_s=1.5, fps_list=(30,), motions=("translational",))
    assert {(r[0], r[4]) for r in rows} == {(v, b) for v in ("filter", "paper") for b in ("gt_oracle", "pvnet")}
    assert all(r[8] < 1.0 for r in rows if r[4] == "gt_oracle")  # the oracle rows: the tracker works
    pvnet = [r for r in rows if r[4] == "pvnet"]
    assert all(r[10] > 0 for r in pvnet)  # requests went out with rendered frames
    seq_dir = next((out / "sequences").iterdir())
    assert any((seq_dir / "rgb").iterdir())  # the frames the PRM sent were rendered
    csv_rows = _csv(out / "table2_pvnet.csv")
    assert list(csv_rows[0]) == table2_vision.HEADER and len(csv_rows) == 2
    text = (out / "table2_pvnet.md").read_text()
    assert "| pvnet | 30 |" in text and "goal 1.5" in text


def test_table2_with_an_unknown_backend_says_what_the_config_serves(tmp_path, capsys):
    assert main(["experiment", "table2", "--backend", "nope", "--out", str(tmp_path / "x"), "--duration", "1"]) == 2
    assert "must serve 'nope'" in capsys.readouterr().err


def test_filter_checks_write_the_peer_cells_with_provenance(tmp_path, capsys):
    out = tmp_path / "filter"
    assert main(["experiment", "filter", "--out", str(out), "--duration", "4", "--in-process", "--seed", "3"]) == 0
    rows = _csv(out / "filter.csv")
    assert {(r["check"], r["fusion"]) for r in rows} == {("peer", "filter"), ("peer", "paper"), ("moving_start", "filter"),
                                                          ("time_offset_20ms", "filter"), ("still_start", "filter")}
    filt = [float(r["proj_px"]) for r in rows if r["check"] == "peer" and r["fusion"] == "filter"]
    paper = [float(r["proj_px"]) for r in rows if r["check"] == "peer" and r["fusion"] == "paper"]
    assert np.mean(filt) < np.mean(paper)  # even 4 s in, the filter is ahead of the paper's reset
    still = next(r for r in rows if r["check"] == "still_start")  # its error and NEES by time after the first pose
    assert np.isfinite(float(still["proj_px_0_1s"])) and np.isfinite(float(still["nees_1_3s"]))
    assert np.isnan(float(still["proj_px_from_10s"]))  # a 4 s run has no frame 10 s after its first pose
    # the Riccati bound beside them, window by window: a still start's first second is bounded lower than a
    # moving start's (whose 4 s run ends within its first second)
    moving = next(r for r in rows if r["check"] == "moving_start")
    assert 0 < float(still["bound_px_0_1s"]) < float(moving["bound_px_0_1s"])
    assert np.isfinite(float(still["bound_px_1_3s"])) and np.isnan(float(moving["bound_px_1_3s"]))
    assert np.isnan(float(next(r for r in rows if r["check"] == "time_offset_20ms")["bound_px_1_3s"]))
    record = json.loads((out / "filter.json").read_text())["provenance"]
    assert record["options"]["seeds"] == [3] and record["date"] and "dirty" in record
    assert "Peer cells" in capsys.readouterr().out


def test_bound_puts_the_filter_beside_the_riccati_bound(tmp_path, capsys):
    out = tmp_path / "bound"
    assert main(["experiment", "bound", "--out", str(out), "--duration", "8", "--fps", "30", "--in-process"]) == 0
    rows = _csv(out / "bound.csv")
    assert list(rows[0]) == ["motion", "level", "fps", "seed", "proj_px_all", "proj_px", "predicted_px", "bound_px",
                             "nees_mean", "nees_rotation", "nees_lo", "nees_hi"]
    assert len(rows) == 6
    assert all(0 < float(r["nees_rotation"]) < float(r["nees_mean"]) for r in rows)  # a part of the whole
    assert all(0 < float(r["nees_lo"]) < 6 < float(r["nees_hi"]) for r in rows)  # each run's own interval
    for r in rows:
        bound, predicted = float(r["bound_px"]), float(r["predicted_px"])
        assert 0.3 < bound < 3.0
        # the filter's covariances are the Riccati solution: on the noisy run they say what the bound says
        assert predicted == pytest.approx(bound, rel=0.1)
    assert "Riccati bound" in capsys.readouterr().out


def test_a_cached_simulated_sequence_that_predates_the_generator_s_declarations_is_made_again(tmp_path):
    """An experiment's `out/.../sequences` cache from before the simulator declared its exact IMU and timing
    (sequence.yaml) would give the tracker a phone's defaults for them: such a sequence is generated again."""
    import yaml

    from flextrack.experiments.common import SimSpec, simulated
    from flextrack.runners.exchange import SIMULATOR_DECLARATIONS as SIMULATOR_DECLARES

    spec = SimSpec("translational", "easy", 10.0, seed=1, duration_s=1.0)
    first = simulated(tmp_path, spec)
    assert all(key in first.meta for key in SIMULATOR_DECLARES)
    meta_path = tmp_path / spec.name / "sequence.yaml"
    old = {k: v for k, v in first.meta.items() if k not in SIMULATOR_DECLARES}
    meta_path.write_text(yaml.safe_dump(old))
    again = simulated(tmp_path, spec)
    assert all(key in again.meta for key in SIMULATOR_DECLARES)
    assert np.array_equal(again.imu.gyro, first.imu.gyro)  # the same seeded sequence
    stamp = meta_path.stat().st_mtime_ns
    assert simulated(tmp_path, spec).meta == again.meta and meta_path.stat().st_mtime_ns == stamp  # kept as it is
