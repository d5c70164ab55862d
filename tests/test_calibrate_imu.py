"""`flextrack calibrate imu`: the time offset, noise and lever arm of a recording against its ground truth."""

import json
from pathlib import Path

import numpy as np
import pytest

from flextrack.calibration import imu as calibration
from flextrack.cli import main
from flextrack.formats import euroc

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
EUROC = DATA / "euroc_v1_02_medium"
PHONE = DATA / "phone_ar" / "nexus5_ar_b"


def test_a_known_delay_of_the_gyro_is_found():
    """The gyro stamped 12 ms late against the truth reads as a 12 ms offset (t_imu = t_camera + offset)."""
    if not EUROC.exists():
        pytest.skip(f"{EUROC} absent (shared data not mounted)")
    imu, gt = calibration.recording(EUROC)
    base, _ = calibration.time_offset(imu, gt)
    late = euroc.ImuData(imu.t_ns + 12_000_000, imu.gyro, imu.accel)
    offset, peak = calibration.time_offset(late, gt)
    assert abs(base) < 0.001 and offset - base == pytest.approx(0.012, abs=0.0005) and peak > 0.9


def test_calibrate_imu_reports_a_phone_and_refuses_a_bad_folder(tmp_path, capsys):
    if not PHONE.exists():
        pytest.skip(f"{PHONE} absent (shared data not mounted)")
    out = tmp_path / "cal.json"
    assert main(["calibrate", "imu", "--data", str(PHONE), "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "time offset" in text and "(yaml: 0.000175" in text and "lever arm" in text
    found = json.loads(out.read_text())
    assert 14.0 < found["imu"]["time_offset_ms"] < 19.0  # the gyro against the motion capture's rate
    assert found["imu"]["gyroscope_noise_density"] > 1.75e-4 and found["provenance"]["commit"] is not None
    assert np.isfinite(found["imu"]["lever_arm_m"]).all()
    assert main(["calibrate", "imu", "--data", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "imu0.csv" in err


def test_the_white_noise_of_a_simulated_phone_is_read_back(tmp_path):
    """A recording whose IMU is its truth plus white noise of the yaml's densities (the test phone): the
    residuals' Allan deviation gives those densities back; 3 s show no clear time-offset peak, and say so."""
    from flextrack.testing.euroc_recording import write_euroc_recording

    data = write_euroc_recording(tmp_path / "my_walk", tmp_path / "work")
    found = calibration.calibrate(data)
    assert found.gyroscope_noise_density == pytest.approx(6.63e-5, rel=0.15)
    assert found.accelerometer_noise_density == pytest.approx(7.35e-4, rel=0.15)
    assert np.isnan(found.time_offset_ms) and found.gaps == 0 and found.truth_jumps == []


def test_a_jump_of_the_truth_is_found_and_its_frames_set_aside(tmp_path):
    """The motion capture's orientation stepping 1 deg where the gyro did not (a marker swap) is found at its
    moment, and `experiment euroc` sets aside the frames in view from just before it to 0.3 s after: scored
    there, a tracker following the IMU would be scored against a pose the device never had."""
    from types import SimpleNamespace

    from flextrack.experiments import euroc as experiment
    from flextrack.geometry import so3
    from flextrack.testing.euroc_recording import write_euroc_recording

    data = write_euroc_recording(tmp_path / "walk", tmp_path / "work")
    assert len(calibration.truth_jumps(*calibration.recording(data), 0.0)) == 0
    gt = euroc.read_groundtruth(data / "groundtruth.csv")
    at = int(gt.t_ns[0] + 1.5e9)  # mid-way through its 3 s
    step = so3.exp(np.radians([1.0, 0.0, 0.0]))
    after = gt.t_ns >= at
    q = gt.q_WB.copy()
    q[after] = [so3.quat_from_matrix(so3.matrix_from_quat(x) @ step) for x in gt.q_WB[after]]
    euroc.write_groundtruth(data / "groundtruth.csv", euroc.GroundTruth(gt.t_ns, gt.p_WB, q, gt.v_WB, gt.bias_gyro,
                                                                        gt.bias_accel))
    jumps = calibration.truth_jumps(*calibration.recording(data), 0.0)
    assert len(jumps) == 1 and abs(jumps[0] - at * 1e-9) < 0.01
    times = gt.t_ns[0] + np.arange(0, 3e9, 1e9 / 30).astype(np.int64)
    ids = np.arange(len(times))
    seq = SimpleNamespace(frame_times_ns=times, frame_ids=ids, gt_T_CO={int(i): np.eye(4) for i in ids[::2]})
    aside = experiment.doubtful_truth(seq, jumps, 0.0)
    expected = {int(i) for i, t in zip(ids[::2], times[::2]) if -0.05e9 <= t - jumps[0] * 1e9 <= 0.3e9}
    assert aside == expected and 4 <= len(aside) <= 6
