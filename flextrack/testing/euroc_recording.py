"""A small recording in the EuRoC layout (imu0.csv, groundtruth.csv, imu0_sensor.yaml, cam0_sensor.yaml), as a
user's own hand-held recording would be: simulated (IMU consistent with the ground truth), already moving
when it starts (no still window), with its own IMU name and camera rate. For the tests of `convert-euroc`,
`track` and `experiment euroc` on one's own data."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import yaml

from flextrack.formats import euroc, kalibr
from flextrack.formats.sequence import load

IMU_NAME = "Test phone IMU (QX-9)"


def write_euroc_recording(root: str | Path, work: str | Path, duration_s: float = 6.0, camera_hz: float = 30.0,
                          seed: int = 0) -> Path:
    """Write `root` (EuRoC layout) from a simulated circular/medium sequence made under `work`; its IMU and
    ground truth start `first_frame_s` into the simulation, when the device already moves."""
    from flextrack.simulator.generate import generate_sequence

    seq = load(generate_sequence("circular", "medium", Path(work) / "sim", duration_s=duration_s, fps=camera_hz,
                                 seed=seed, still_s=1.0, moving_start=True))
    start_ns = int(seq.frame_times_ns[0])  # the simulator's first frame: the device moving for 1 s already
    keep = seq.imu.t_ns >= start_ns
    imu = dataclasses.replace(seq.imu, t_ns=seq.imu.t_ns[keep], gyro=seq.imu.gyro[keep], accel=seq.imu.accel[keep])
    gt = seq.groundtruth
    keep_gt = gt.t_ns >= start_ns
    gt = euroc.GroundTruth(*(np.asarray(getattr(gt, f.name))[keep_gt] for f in dataclasses.fields(gt)))
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    euroc.write_imu(root / "imu0.csv", imu)
    euroc.write_groundtruth(root / "groundtruth.csv", gt)
    kalibr.write_imu_sensor(root / "imu0_sensor.yaml", seq.imu_noise, np.eye(4), comment=IMU_NAME)
    cam = seq.camera
    (root / "cam0_sensor.yaml").write_text(yaml.safe_dump({
        "sensor_type": "camera", "comment": "test camera",
        "T_BS": {"cols": 4, "rows": 4, "data": [float(x) for x in seq.T_BC.ravel()]},
        "rate_hz": float(camera_hz), "resolution": [int(cam.width), int(cam.height)], "camera_model": "pinhole",
        "intrinsics": [float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy)], "distortion_model": "radial-tangential",
        "distortion_coefficients": [0.0, 0.0, 0.0, 0.0]}, sort_keys=False))
    return root
