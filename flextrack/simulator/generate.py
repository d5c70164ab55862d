"""One synthetic sequence folder from a motion program: IMU, ground truth, frame times, poses.

Timeline (s from the first IMU sample): the device is still on [0, still_s) (the tracker
initialises gravity and gyro bias there), the program eases in over 2 s and moves for
`duration_s`; frames run from `first_frame_s` (>= 1 s after the IMU starts) to the end.
The object stands on the table at the world origin with a seeded heading; the rig is a phone:
the IMU is the body B, the rear camera C sits beside it (T_BC).
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np

from flextrack import assets
from flextrack.formats.euroc import GroundTruth
from flextrack.formats.sequence import Sequence
from flextrack.geometry import se3, so3
from flextrack.geometry.camera import PinholeCamera
from flextrack.runners.exchange import SIMULATOR_DECLARATIONS
from flextrack.simulator import default_object, imu
from flextrack.simulator.render import load_model
from flextrack.simulator.sequence_writer import bop_obj_id_of, install_model, write_sequence
from flextrack.simulator.trajectory import MotionProgram

# Phone rear camera beside its IMU: B is the phone's sensor frame (x right, y up the screen, z out of
# the screen); the camera looks out of the back (z_C = -z_B), image x along x_B, image y along -y_B,
# 4.5 cm up the phone, 1.5 cm left and 5 mm behind the IMU.
T_BC_PHONE = se3.make(np.diag([1.0, -1.0, -1.0]), np.array([-0.015, 0.045, -0.005]))
STILL_S = 2.0
FIRST_FRAME_S = 1.0


def object_pose_on_table(model_path: Path, seed: int) -> np.ndarray:
    """T_WO: the model standing on the table top (z = 0) at the origin, turned by a seeded heading."""
    vertices = np.asarray(load_model(model_path).vertices)
    heading = np.random.default_rng([seed, 0x0B]).uniform(-np.pi, np.pi)
    return se3.make(so3.exp(np.array([0.0, 0.0, heading])), np.array([0.0, 0.0, -vertices[:, 2].min()]))


def generate_sequence(motion: str, level: str, out_dir: str | Path, *, duration_s: float = 30.0,
                      fps: float = 120.0, imu_rate: float = 200.0, seed: int = 0,
                      object_path: str | Path | None = None, object_id: str | None = None,
                      imu_profile: str = "pixel2", imu_jitter_s: float = 0.0, T_BC: np.ndarray | None = None,
                      still_s: float = STILL_S, first_frame_s: float = FIRST_FRAME_S, moving_start: bool = False,
                      imu_time_offset_s: float = 0.0, render: bool = False) -> Path:
    """Write the sequence folder `out_dir` and return it (see the module docstring).

    `moving_start`: the first frame comes 1 s after the program reached full speed, so a tracker starts
    on a moving device (no still window before its first frame). `imu_time_offset_s`: the IMU stamps
    its samples this late (t_imu = t_camera + offset, the offset a tracker may estimate).
    """
    if fps <= 0 or imu_rate <= 0 or duration_s <= 0:
        raise ValueError("fps, imu_rate and duration_s must be positive")
    if still_s < 1.0 or not 1.0 <= first_frame_s <= still_s + duration_s:
        raise ValueError("the IMU must start >= 1 s before the first frame, with >= 1 s still")
    prof = imu.profile(imu_profile, imu_rate)
    source = Path(object_path) if object_path is not None else assets.default_object_model()
    if object_id is None:
        object_id = default_object.OBJECT_ID if object_path is None else source.stem
    bop_obj_id = default_object.BOP_OBJ_ID if object_path is None else bop_obj_id_of(source)
    root = Path(out_dir)
    model = install_model(source, root, bop_obj_id)

    T_BC = T_BC_PHONE if T_BC is None else np.asarray(T_BC, float)
    T_WO = object_pose_on_table(model, seed)
    centre_O = np.mean(np.asarray(load_model(model).bounds), axis=0)
    program = MotionProgram(motion, level, seed, still_s=still_s, duration_s=duration_s,
                            target_W=se3.transform_points(T_WO, centre_O[None])[0])
    if moving_start:
        first_frame_s = still_s + program.ramp_s + 1.0
        if first_frame_s >= program.end_s:
            raise ValueError(f"--moving-start needs a duration over {program.ramp_s + 1.0:g} s")

    rng = np.random.default_rng([seed, 0x1A0])
    t_imu = imu.sample_times(0.0, program.end_s, imu_rate, imu_jitter_s, rng)
    body = program.camera(t_imu).attached(se3.inverse(T_BC))
    record = imu.synthesize(t_imu, body, prof, rng)
    stamped = replace(record.imu, t_ns=record.imu.t_ns + round(imu_time_offset_s * 1e9))
    q_WB = np.array([so3.quat_from_matrix(R) for R in body.R_WX])
    groundtruth = GroundTruth(record.imu.t_ns, body.p_WX, q_WB, body.v_WX, record.bias_gyro, record.bias_accel)

    n_frames = int(np.floor((program.end_s - first_frame_s) * fps + 1e-9)) + 1
    t_frames = first_frame_s + np.arange(n_frames) / fps
    T_WC = program.camera(t_frames).poses()
    T_CW = np.linalg.inv(T_WC)
    frame_ids = np.arange(n_frames)
    stats = program.statistics()
    seq = Sequence(
        root=root, imu=stamped, imu_noise=prof.noise, frame_ids=frame_ids,
        frame_times_ns=np.round(t_frames * 1e9).astype(np.int64),
        gt_T_CO={int(i): T_CW[i] @ T_WO for i in frame_ids}, camera=PinholeCamera.linemod(), T_BC=T_BC,
        T_WO=T_WO, object_id=object_id, bop_obj_id=bop_obj_id, model_path=model, groundtruth=groundtruth,
        meta={
            "generator": {
                "motion": motion, "level": level, "seed": int(seed), "duration_s": float(duration_s),
                "fps": float(fps), "imu_rate_hz": float(imu_rate), "imu_profile": prof.name,
                "imu_jitter_s": float(imu_jitter_s), "still_s": float(still_s), "ramp_s": program.ramp_s,
                "first_frame_s": float(first_frame_s), "moving_start": bool(moving_start),
                "imu_time_offset_s": float(imu_time_offset_s), "object": str(object_path or "default"),
                "scene_seed": int(seed),
            },
            "times_ns": {"imu_start": int(record.imu.t_ns[0]), "motion_start": round(still_s * 1e9),
                         "end": int(record.imu.t_ns[-1])},
            "imu_bias": {"gyro_turn_on": record.bias_gyro[0].tolist(), "accel_turn_on": record.bias_accel[0].tolist()},
            "statistics": stats,
            # what the tracker's answer floor and gyro scale error stand for is exact here (flextrack.runners.exchange)
            **SIMULATOR_DECLARATIONS,
        },
    )
    write_sequence(seq, imu_extra={
        "profile": prof.name, "profile_comment": prof.comment,
        "gyroscope_turn_on_bias_sigma": prof.gyro_bias_sigma,  # rad/s, per axis (1 sigma)
        "accelerometer_turn_on_bias_sigma": prof.accel_bias_sigma,  # m/s^2
    })
    if render:
        from flextrack.simulator.frames import render_sequence
        render_sequence(root)
    return root
