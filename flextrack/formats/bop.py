"""BOP scene files (scene_gt.json, scene_camera.json) and models_info.json. BOP uses mm."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def read_scene_gt(path: str | Path, obj_id: int | None = None) -> dict[int, np.ndarray]:
    """frame id -> T_CO (4x4, metres) of `obj_id` (or of the first object when None)."""
    doc = json.loads(Path(path).read_text())
    poses: dict[int, np.ndarray] = {}
    for frame, frame_annotations in doc.items():
        for ann in frame_annotations:
            if obj_id is not None and int(ann["obj_id"]) != obj_id:
                continue
            T = np.eye(4)
            T[:3, :3] = np.asarray(ann["cam_R_m2c"], dtype=float).reshape(3, 3)
            T[:3, 3] = np.asarray(ann["cam_t_m2c"], dtype=float) / 1000.0
            poses[int(frame)] = T
            break
    return poses


def write_scene_gt(path: str | Path, poses: dict[int, np.ndarray], obj_id: int) -> None:
    doc = {
        str(frame): [
            {
                "cam_R_m2c": [float(x) for x in T[:3, :3].ravel()],
                "cam_t_m2c": [float(x) for x in T[:3, 3] * 1000.0],
                "obj_id": int(obj_id),
            }
        ]
        for frame, T in sorted(poses.items())
    }
    Path(path).write_text(json.dumps(doc, indent=1))


def read_scene_camera(path: str | Path) -> dict[int, np.ndarray]:
    """frame id -> 3x3 K."""
    doc = json.loads(Path(path).read_text())
    return {int(k): np.asarray(v["cam_K"], dtype=float).reshape(3, 3) for k, v in doc.items()}


def write_scene_camera(path: str | Path, Ks: dict[int, np.ndarray]) -> None:
    doc = {str(k): {"cam_K": [float(x) for x in K.ravel()], "depth_scale": 1.0} for k, K in sorted(Ks.items())}
    Path(path).write_text(json.dumps(doc, indent=1))


def read_models_info(path: str | Path) -> dict[int, dict]:
    return {int(k): v for k, v in json.loads(Path(path).read_text()).items()}


def write_models_info(path: str | Path, info: dict[int, dict]) -> None:
    Path(path).write_text(json.dumps({str(k): v for k, v in info.items()}, indent=1))


def symmetry_transforms(info: dict, max_sym_disc_step: float = 0.01) -> np.ndarray:
    """(S, 4, 4) transforms in metres that map the model onto itself, identity first: models_info.json's
    `symmetries_discrete` (4x4, mm) and `symmetries_continuous` (axis, offset in mm) discretised and combined
    as bop_toolkit's get_symmetry_transformations does (a continuous one in ceil(pi / max_sym_disc_step)
    steps, a step moving a point at the diameter's distance by at most max_sym_disc_step diameters)."""
    discrete = [np.eye(4)]
    for sym in info.get("symmetries_discrete", []):
        T = np.asarray(sym, dtype=float).reshape(4, 4).copy()
        T[:3, 3] /= 1000.0
        discrete.append(T)
    continuous = []
    for sym in info.get("symmetries_continuous", []):
        axis = np.asarray(sym["axis"], dtype=float)
        axis /= np.linalg.norm(axis)
        offset = np.asarray(sym.get("offset", [0.0, 0.0, 0.0]), dtype=float) / 1000.0
        steps = int(np.ceil(np.pi / max_sym_disc_step))
        for i in range(steps):
            angle = 2.0 * np.pi * i / steps
            K = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
            R = np.eye(3) + np.sin(angle) * K + (1.0 - np.cos(angle)) * K @ K
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R, offset - R @ offset
            continuous.append(T)
    if not continuous:
        return np.array(discrete)
    return np.array([C @ D for D in discrete for C in continuous])
