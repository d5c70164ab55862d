"""EuRoC V1_02 as a sequence folder: real IMU kept, virtual object seen, IMU consistent with Vicon."""

import json
from pathlib import Path

import numpy as np
import pytest

from flextrack import assets
from flextrack.cli import main as flextrack_main
from flextrack.formats import euroc
from flextrack.formats.sequence import load
from flextrack.geometry import se3, so3
from flextrack.simulator.euroc_convert import convert_euroc, visibility
from flextrack.simulator.integrate import integrate
from flextrack.simulator.render import load_model

EUROC = Path(__file__).resolve().parents[2] / "shared" / "data" / "euroc_v1_02_medium"
pytestmark = pytest.mark.skipif(not EUROC.exists(), reason=f"{EUROC} absent (shared data not mounted)")


@pytest.fixture(scope="module")
def converted(tmp_path_factory) -> Path:
    return convert_euroc(EUROC, tmp_path_factory.mktemp("euroc") / "v1_02")


def test_real_imu_and_calibration_are_kept(converted):
    seq = load(converted)
    source = euroc.read_imu(EUROC / "imu0.csv")
    assert np.array_equal(seq.imu.t_ns, source.t_ns) and np.allclose(seq.imu.accel, source.accel)
    assert seq.camera.width == 752 and seq.camera.fx == pytest.approx(458.654)
    assert seq.T_BC[0, 3] == pytest.approx(-0.0216401454975)
    assert seq.imu_noise.gyroscope_noise_density == pytest.approx(1.6968e-4)
    assert np.allclose(np.diff(seq.frame_times_ns), 50_000_000)


def test_frames_start_inside_the_still_start_with_backfilled_ground_truth(converted):
    seq = load(converted)
    lead = seq.frame_times_ns[0] - seq.imu.t_ns[0]
    assert 500_000_000 <= lead < 700_000_000  # 0.5 s still IMU before the first frame, the MAV still
    window = (seq.imu.t_ns > seq.frame_times_ns[0] - 500_000_000) & (seq.imu.t_ns <= seq.frame_times_ns[0])
    assert np.abs(seq.imu.gyro[window] - seq.imu.gyro[window].mean(axis=0)).max() < 0.02
    # frames before the Vicon record starts have poses (extrapolated back from its first state),
    # continuous with the recorded ones, and nearly still (the MAV moves at ~1 cm/s then)
    early = seq.frame_times_ns < seq.groundtruth.t_ns[0]
    assert early.sum() >= 8 and all(int(i) in seq.gt_T_CO for i in seq.frame_ids)
    first_recorded = int(np.argmax(~early))
    steps = [np.linalg.norm(seq.gt_T_CO[i + 1][:3, 3] - seq.gt_T_CO[i][:3, 3]) for i in range(first_recorded + 2)]
    assert max(steps) < 0.02  # m per 50 ms frame: no jump where the backfill meets Vicon
    assert steps[0] < 1e-3


def test_scaled_object_is_written_and_small_objects_are_refused(converted, tmp_path):
    seq = load(converted)
    info = json.loads((converted / "models" / "models_info.json").read_text())
    default_info = json.loads((assets.default_object_dir() / "models_info.json").read_text())
    assert next(iter(info.values()))["diameter"] == pytest.approx(4 * next(iter(default_info.values()))["diameter"],
                                                                     rel=1e-3)
    assert seq.meta["converter"]["object_scale"] == 4.0
    with pytest.raises(ValueError, match="object scale of at least"):
        convert_euroc(EUROC, tmp_path / "small", object_scale=1.0)


def test_object_placed_where_cam0_sees_it(converted):
    seq = load(converted)
    _, T_CO = seq.gt_times_and_poses()
    T_WC = seq.T_WO[None] @ np.linalg.inv(T_CO)
    centre = seq.meta["placement"]["centre_W"]
    vertices = np.asarray(load_model(seq.model_path).vertices)
    radius = float(np.linalg.norm(vertices - (vertices.min(axis=0) + vertices.max(axis=0)) / 2, axis=1).max())
    reach = seq.meta["converter"]["placement_distance_m"]
    seen = visibility(np.array([centre]), T_WC, seq.camera, radius, reach)[0]
    assert seen.mean() > 0.2  # the drone looks all around the room; this is the best single spot
    assert seen.mean() == pytest.approx(seq.meta["placement"]["visible_fraction"], abs=0.01)
    # scene_gt is the Vicon pose at the frame time, moved to cam0 by T_BC
    gt = seq.groundtruth
    poses = np.stack([se3.from_quat_translation(q, p) for q, p in zip(gt.q_WB, gt.p_WB)])
    for i in seq.frame_ids[seq.frame_times_ns >= gt.t_ns[0]][::50]:
        T_WB = se3.interpolate_at(gt.t_ns, poses, int(seq.frame_times_ns[i]))
        assert np.allclose(se3.inverse(T_WB @ seq.T_BC) @ seq.T_WO, seq.gt_T_CO[int(i)], atol=1e-9)


def test_imu_integrated_with_gt_biases_follows_vicon_orientation(converted):
    seq = load(converted)
    gt, imu = seq.groundtruth, seq.imu
    inside = (imu.t_ns >= gt.t_ns[0]) & (imu.t_ns <= gt.t_ns[-1])
    t_ns = imu.t_ns[inside]
    poses = np.stack([se3.from_quat_translation(q, p) for q, p in zip(gt.q_WB, gt.p_WB)])
    T0 = se3.interpolate_at(gt.t_ns, poses, int(t_ns[0]))
    biases = [np.stack([np.interp(t_ns, gt.t_ns, b[:, k]) for k in range(3)], axis=1)
              for b in (gt.bias_gyro, gt.bias_accel)]
    v0 = np.array([np.interp(t_ns[0], gt.t_ns, gt.v_WB[:, k]) for k in range(3)])
    result = integrate((t_ns - t_ns[0]) / 1e9, imu.gyro[inside], imu.accel[inside], T0[:3, :3], T0[:3, 3], v0,
                       bias_gyro=biases[0], bias_accel=biases[1])
    errors = [so3.angle_deg(result.R_WB[i] @ se3.interpolate_at(gt.t_ns, poses, int(t_ns[i]))[:3, :3].T)
              for i in range(0, len(t_ns), 10)]
    assert (t_ns[-1] - t_ns[0]) / 1e9 > 38.0
    assert max(errors) < 1.0


def test_any_frame_rate_and_cli(tmp_path, capsys):
    root = convert_euroc(EUROC, tmp_path / "fps60", fps=60.0)
    seq = load(root)
    assert np.allclose(np.diff(seq.frame_times_ns), 1e9 / 60, atol=1)
    rc = flextrack_main(["convert-euroc", "--euroc", str(EUROC), "--out", str(tmp_path / "cli"), "--no-plots"])
    assert rc == 0 and "seen whole in" in capsys.readouterr().out
    rc = flextrack_main(["convert-euroc", "--euroc", str(tmp_path), "--out", str(tmp_path / "bad")])
    assert rc == 2 and "no EuRoC recording" in capsys.readouterr().err


def test_the_object_stays_where_it_is_at_any_frame_rate(tmp_path):
    """Placed from the camera's path at a fixed rate, not at the frames' (it moved 0.51 m between 30 and 52
    FPS on a phone recording)."""
    placed = [load(convert_euroc(EUROC, tmp_path / f"fps{fps}", fps=fps)).T_WO for fps in (30.0, 52.0)]
    assert np.allclose(placed[0], placed[1])


def test_the_converted_sequence_is_named_by_its_data_not_by_file_times(tmp_path):
    """The name keys the Noisy oracle's draws: a copy of the same data, touched, must get the same draws
    (and be converted again, since a changed file is not trusted)."""
    import os
    import shutil

    from flextrack.experiments import euroc as experiment

    data = tmp_path / "copy" / EUROC.name
    shutil.copytree(EUROC, data)
    first = experiment.converted(tmp_path / "out", data, 20.0, experiment.OBJECT_SCALE, None, None)
    stamp = (first / "converter.sha256").read_text()
    os.utime(data / "imu0.csv", ns=(1, 1))
    again = experiment.converted(tmp_path / "out", data, 20.0, experiment.OBJECT_SCALE, None, None)
    assert again == first
    assert (again / "converter.sha256").read_text() != stamp  # remade
