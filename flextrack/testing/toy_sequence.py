"""A tiny sequence folder (a box, the camera circling it) for oracle tests and the service benchmark."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from flextrack.formats import euroc, kalibr
from flextrack.formats import sequence as sequence_io
from flextrack.geometry import se3, so3
from flextrack.geometry.camera import PinholeCamera


def orbit_pose(angle: float, radius_m: float = 0.6) -> np.ndarray:
    """T_CO of a camera on a circle around the object, looking at it, the object slowly spinning."""
    R = so3.exp(np.array([0.3, angle, 0.1 * np.sin(3 * angle)]))
    t = np.array([0.05 * np.cos(angle), 0.03 * np.sin(angle), radius_m])
    return se3.make(R, t)


def write_orbit_sequence(root: str | Path, frames: int = 30, fps: float = 30.0, object_id: str = "toy",
                         start_ns: int = 1_000_000_000, missing: tuple[int, ...] = ()) -> sequence_io.Sequence:
    """Write the folder (model, frame times, BOP ground truth, a flat IMU) and return it.

    Frame ids in `missing` get no ground truth, as when the object is hidden.
    """
    root = Path(root)
    (root / "models").mkdir(parents=True, exist_ok=True)
    model_path = root / "models" / "obj_000001.ply"
    trimesh.creation.box(extents=(80.0, 60.0, 40.0)).export(model_path)
    ids = np.arange(frames, dtype=np.int64)
    times = start_ns + np.round(ids * 1e9 / fps).astype(np.int64)
    gt = {int(i): orbit_pose(2 * np.pi * i / frames) for i in ids if int(i) not in missing}
    imu_t = np.arange(times[0] - 10_000_000, times[-1] + 10_000_000, 5_000_000, dtype=np.int64)
    imu = euroc.ImuData(imu_t, np.zeros((len(imu_t), 3)), np.tile([0.0, 0.0, 9.81], (len(imu_t), 1)))
    seq = sequence_io.Sequence(
        root=root, imu=imu, imu_noise=kalibr.ImuNoise(6.63e-5, 1e-5, 7.35e-4, 1e-4, 200.0),
        frame_ids=ids, frame_times_ns=times, gt_T_CO=gt, camera=PinholeCamera.linemod(),
        T_BC=np.eye(4), T_WO=np.eye(4), object_id=object_id, bop_obj_id=1, model_path=model_path)
    sequence_io.save(seq)
    return seq
