"""Write a sequence folder: `flextrack.formats.sequence.save` plus what the simulator adds beside it.

Beside the shared writer's files this puts the object's BOP model into `models/`, an EuRoC-style
`cam0/sensor.yaml` (intrinsics, distortion, T_BS = T_BC, rate) and the bias figures of the IMU
profile into `imu0/sensor.yaml` (extra keys; Kalibr readers ignore them).
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import yaml

from flextrack.formats import bop
from flextrack.formats.sequence import Sequence, save
from flextrack.simulator.default_object import models_info
from flextrack.simulator.render import load_model


def bop_obj_id_of(model_path: Path) -> int:
    """BOP object id from a model's file name (obj_000006.ply -> 6), 1 when it has none."""
    match = re.fullmatch(r"obj_(\d+)", model_path.stem)
    return int(match.group(1)) if match else 1


def install_model(model_path: str | Path, root: Path, bop_obj_id: int) -> Path:
    """Copy the model into root/models as obj_<id>.ply with its models_info.json; returns the copy."""
    src = Path(model_path)
    if not src.is_file():
        raise FileNotFoundError(f"object model {src} does not exist")
    models = root / "models"
    models.mkdir(parents=True, exist_ok=True)
    dst = models / f"obj_{bop_obj_id:06d}.ply"
    shutil.copyfile(src, dst)
    info_src = src.parent / "models_info.json"
    info = bop.read_models_info(info_src) if info_src.exists() else {}
    entry = info.get(bop_obj_id_of(src)) or models_info(np.asarray(load_model(src).vertices) * 1000.0)
    bop.write_models_info(models / "models_info.json", {bop_obj_id: entry})
    return dst


def write_camera_sensor(path: Path, seq: Sequence, rate_hz: float) -> None:
    cam = seq.camera
    doc = {
        "sensor_type": "camera",
        "comment": f"camera of flextrack sequence {seq.name}",
        "T_BS": {"cols": 4, "rows": 4, "data": [float(x) for x in np.asarray(seq.T_BC).ravel()]},
        "rate_hz": float(rate_hz),
        "resolution": [int(cam.width), int(cam.height)],
        "camera_model": "pinhole",
        "intrinsics": [float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy)],
        "distortion_model": "radial-tangential",
        "distortion_coefficients": [float(x) for x in (cam.distortion or (0.0, 0.0, 0.0, 0.0))],
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))


def write_sequence(seq: Sequence, imu_extra: dict | None = None) -> Path:
    """Save `seq` (its model must already be under seq.root) and the simulator's extra files.

    Frames rendered for an earlier sequence written to the same folder are removed: they would
    otherwise be read back as this one's."""
    for stale in ("rgb", "mask", "depth"):
        shutil.rmtree(seq.root / stale, ignore_errors=True)
    save(seq)
    times = seq.frame_times_ns
    rate = float(1e9 * (len(times) - 1) / (times[-1] - times[0])) if len(times) > 1 else 0.0
    write_camera_sensor(seq.root / "cam0" / "sensor.yaml", seq, rate)
    if imu_extra:
        imu_yaml = seq.root / "imu0" / "sensor.yaml"
        doc = yaml.safe_load(imu_yaml.read_text())
        doc.update(imu_extra)
        imu_yaml.write_text(yaml.safe_dump(doc, sort_keys=False))
    return seq.root
