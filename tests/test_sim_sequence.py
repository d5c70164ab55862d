"""Sequence folders: what the generator writes reads back consistently, renders, and is reproducible."""

from pathlib import Path

import cv2
import numpy as np
import pytest

from flextrack.cli import main as flextrack_main
from flextrack.formats import bop, kalibr
from flextrack.formats.sequence import load
from flextrack.geometry import se3
from flextrack.geometry.camera import project_model
from flextrack.simulator.frames import SequenceFrames
from flextrack.simulator.generate import generate_sequence
from flextrack.simulator.plots import plot_sequence

CAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmo" / "models" / "obj_000006.ply"


@pytest.fixture(scope="module")
def short_sequence(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("seq") / "circular_hard"
    return generate_sequence("circular", "hard", out, duration_s=4.0, fps=30.0, imu_rate=200.0, seed=4)


def test_folder_layout_and_timeline(short_sequence):
    seq = load(short_sequence)
    for part in ("imu0/data.csv", "imu0/sensor.yaml", "cam0/sensor.yaml", "frame_times.csv", "scene_gt.json",
                 "scene_camera.json", "groundtruth.csv", "rig.yaml", "sequence.yaml", "models/obj_000001.ply",
                 "models/models_info.json"):
        assert (short_sequence / part).is_file(), part
    assert seq.object_id == "default" and seq.bop_obj_id == 1
    assert seq.imu.t_ns[0] <= seq.frame_times_ns[0] - 1_000_000_000
    assert np.allclose(np.diff(seq.frame_times_ns), 1e9 / 30, atol=1)
    assert np.allclose(np.diff(seq.imu.t_ns), 5_000_000, atol=1)
    assert seq.imu.t_ns[-1] >= seq.frame_times_ns[-1]
    assert len(seq.gt_T_CO) == len(seq.frame_ids)
    still = seq.imu.t_ns < seq.meta["times_ns"]["motion_start"]
    assert (seq.imu.t_ns[still][-1] - seq.imu.t_ns[0]) / 1e9 >= 1.0
    assert np.allclose(np.linalg.norm(seq.imu.accel[still], axis=1), 9.81, atol=0.2)  # gravity, bias, noise
    noise, _ = kalibr.read_imu_sensor(short_sequence / "imu0" / "sensor.yaml")
    assert noise.gyroscope_noise_density == pytest.approx(6.63e-5)
    cam = kalibr.read_camera_sensor(short_sequence / "cam0" / "sensor.yaml")
    assert np.allclose(cam.T_BS, seq.T_BC) and np.allclose(cam.K, seq.camera.K)
    assert seq.meta["statistics"]["table3"]["avg_speed_m_s"] == 0.229


def test_groundtruth_rig_and_scene_gt_agree(short_sequence):
    seq = load(short_sequence)
    gt = seq.groundtruth
    poses = np.stack([se3.from_quat_translation(q, p) for q, p in zip(gt.q_WB, gt.p_WB)])
    for i in seq.frame_ids[::7]:
        T_WB = se3.interpolate_at(gt.t_ns, poses, int(seq.frame_times_ns[i]))
        T_CO = se3.inverse(T_WB @ seq.T_BC) @ seq.T_WO
        assert np.allclose(T_CO, seq.gt_T_CO[int(i)], atol=2e-4)  # linear interpolation between 5 ms samples
    # the bias columns are what was added: at rest, gyro minus bias is noise only
    still = seq.imu.t_ns < seq.meta["times_ns"]["motion_start"]
    assert np.abs((seq.imu.gyro - gt.bias_gyro)[still].mean(axis=0)).max() < 2e-4


def test_rendered_frames_match_scene_gt(short_sequence):
    seq = load(short_sequence)
    with SequenceFrames(seq) as frames:
        for i in (0, len(seq.frame_ids) // 2, len(seq.frame_ids) - 1):
            frame = frames.frame(int(i))  # lazily rendered and written
            T_CO = bop.read_scene_gt(short_sequence / "scene_gt.json", 1)[int(i)]
            mesh = frames._gl().mesh
            uv = project_model(seq.camera, T_CO, np.asarray(mesh.vertices))
            s = 8
            fine = np.zeros((seq.camera.height * s, seq.camera.width * s), np.uint8)
            for tri in np.round(uv[mesh.faces] * s * 16).astype(np.int32):
                cv2.fillConvexPoly(fine, tri, 1, shift=4)
            ref = fine[::s, ::s].astype(bool)
            iou = (ref & frame.mask).sum() / (ref | frame.mask).sum()
            assert iou >= 0.98
            ys, xs = np.nonzero(frame.mask)
            ry, rx = np.nonzero(ref)
            assert np.hypot(xs.mean() - rx.mean(), ys.mean() - ry.mean()) < 1.0
            again = frames.frame(int(i))  # now read back from disk
            assert np.array_equal(again.mask, frame.mask) and np.array_equal(again.rgb, frame.rgb)
            assert np.allclose(again.depth, frame.depth, atol=1e-3)
    assert (short_sequence / "rgb" / "000000.png").is_file()


def test_same_seed_same_bytes(tmp_path):
    a = generate_sequence("translational", "medium", tmp_path / "a", duration_s=2.0, fps=30.0, seed=9)
    b = generate_sequence("translational", "medium", tmp_path / "b", duration_s=2.0, fps=30.0, seed=9)
    c = generate_sequence("translational", "medium", tmp_path / "c", duration_s=2.0, fps=30.0, seed=10)
    for name in ("imu0/data.csv", "groundtruth.csv", "scene_gt.json"):
        assert (a / name).read_bytes() == (b / name).read_bytes()
        assert (a / name).read_bytes() != (c / name).read_bytes()


def test_any_bop_model_and_ideal_profile(tmp_path):
    if not CAT.exists():
        pytest.skip(f"{CAT} absent (shared data not mounted)")
    root = generate_sequence("translational", "easy", tmp_path / "cat", duration_s=2.0, fps=15.0, object_path=CAT,
                             imu_profile="ideal")
    seq = load(root)
    assert seq.object_id == "obj_000006" and seq.bop_obj_id == 6
    assert (root / "models" / "obj_000006.ply").is_file()
    assert bop.read_models_info(root / "models" / "models_info.json")[6]["diameter"] == pytest.approx(154.546)
    assert np.abs(seq.groundtruth.bias_gyro).max() == 0.0
    with SequenceFrames(seq) as frames:
        assert frames.render(0).mask.sum() > 500


def test_cli_writes_sequence_and_pictures(tmp_path, capsys):
    out = tmp_path / "cli"
    rc = flextrack_main(["simulate", "--motion", "translational", "--level", "hard", "--duration", "2",
                         "--fps", "30", "--imu-profile", "euroc", "--out", str(out)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "Table 3" in printed and "avg speed" in printed
    assert (out / "plots" / "trajectory.png").stat().st_size > 10_000
    assert (out / "plots" / "imu.png").stat().st_size > 10_000
    rc = flextrack_main(["simulate", "--motion", "translational", "--object", str(tmp_path / "nope.ply"),
                         "--out", str(tmp_path / "bad")])
    assert rc == 2 and "does not exist" in capsys.readouterr().err


def test_static_sequence_plots_allan(tmp_path):
    root = generate_sequence("static", "easy", tmp_path / "static", duration_s=20.0, fps=10.0)
    paths = plot_sequence(root)
    assert any(p.name == "allan.png" for p in paths)


def test_bad_arguments_are_clear_errors(tmp_path):
    with pytest.raises(ValueError):
        generate_sequence("circular", "easy", tmp_path / "x", fps=0.0)
    with pytest.raises(ValueError):
        generate_sequence("circular", "easy", tmp_path / "x", still_s=0.5)
    with pytest.raises(ValueError):
        generate_sequence("circular", "impossible", tmp_path / "x")


def test_regenerating_a_folder_drops_stale_frames(tmp_path):
    root = tmp_path / "again"
    (root / "rgb").mkdir(parents=True)
    (root / "rgb" / "000000.png").write_bytes(b"old frame")
    generate_sequence("translational", "easy", root, duration_s=1.0, fps=10.0)
    assert not (root / "rgb").exists()
