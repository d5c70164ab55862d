"""Object registry: object_id -> model (BOP .ply in mm, held in metres), 3D keypoints and 3D box.

Keypoints are what PnP-style estimators match 2D detections against: the ones given in the
config, or K points farthest-point-sampled from the model's vertices plus the box centre last
(PVNet's choice), so keypoint id i is row i of `ObjectModel.keypoints`. A BOP model's diameter and
symmetries come from the models_info.json beside it; `load_object_folder` reads a whole BOP models
folder (what `flextrack serve --objects DIR` serves).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from estimators.base import UnknownObject
from flextrack.assets import resolve
from flextrack.formats import bop
from flextrack.geometry.camera import bbox_corners

DEFAULT_KEYPOINT_COUNT = 8


@dataclass(frozen=True)
class ObjectModel:
    object_id: str
    model_path: Path
    vertices: np.ndarray  # (N, 3) m, object frame
    keypoints: np.ndarray  # (K, 3) m; keypoint id = row
    bbox_corners: np.ndarray  # (8, 3) m
    diameter_m: float
    faces: np.ndarray  # (F, 3) rows of `vertices`: the mesh, for estimators that draw the object
    # (S, 4, 4) transforms in metres that leave the model's look unchanged, identity first (BOP's models_info.json,
    # continuous ones discretised as bop_toolkit does): scoring takes a pose up to these (ADD-S, proj over them)
    symmetries: np.ndarray = field(default_factory=lambda: np.eye(4)[None])


def farthest_point_sample(points: np.ndarray, k: int) -> np.ndarray:
    """k rows of `points` spread out greedily, starting from the one farthest from the centroid."""
    if k > len(points):
        raise ValueError(f"cannot sample {k} keypoints from {len(points)} vertices")
    chosen = [int(np.argmax(np.linalg.norm(points - points.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(k - 1):
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return points[chosen]


BOP_MODEL = re.compile(r"obj_(\d+)")


def _models_info(model_path: Path) -> dict | None:
    """This model's entry of the models_info.json beside it (BOP), or None."""
    info_path = model_path.parent / "models_info.json"
    match = BOP_MODEL.fullmatch(model_path.stem)
    if not (match and info_path.is_file()):
        return None
    try:
        return bop.read_models_info(info_path).get(int(match.group(1)))
    except (ValueError, OSError) as exc:
        raise ValueError(f"{info_path}: not a readable models_info.json ({exc})") from None


def _diameter_m(vertices: np.ndarray, info: dict | None) -> float:
    """BOP's diameter from models_info.json when it lists this object, else computed."""
    if info and "diameter" in info:
        return float(info["diameter"]) / 1000.0
    hull = trimesh.PointCloud(vertices).convex_hull.vertices
    return float(np.max(np.linalg.norm(hull[:, None, :] - hull[None, :, :], axis=2)))


def load_object(object_id: str, model_path: str | Path, keypoints=None,
                keypoint_count: int = DEFAULT_KEYPOINT_COUNT) -> ObjectModel:
    """Read a .ply in mm. `keypoints`: (K, 3) in metres, a text/.npy file of them, or None to sample."""
    model_path = Path(model_path)
    if not model_path.is_file():
        raise FileNotFoundError(f"object '{object_id}': model file {model_path} not found")
    try:
        geometry = trimesh.load(model_path, process=False)
        vertices = np.asarray(geometry.vertices, dtype=float) / 1000.0
    except Exception as exc:  # noqa: BLE001 - a parser's own error on a damaged file: say which file, in one line
        raise ValueError(f"object '{object_id}': model {model_path} does not load as a mesh "
                         f"({type(exc).__name__}: {exc})") from None
    if vertices.ndim != 2 or len(vertices) == 0 or not np.all(np.isfinite(vertices)):
        raise ValueError(f"object '{object_id}': model {model_path} has no (finite) vertices")
    corners = bbox_corners(vertices)
    if keypoints is None:
        kp = np.vstack([farthest_point_sample(vertices, keypoint_count), corners.mean(axis=0)])
    elif isinstance(keypoints, (str, Path)):
        path = Path(keypoints)
        kp = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, ndmin=2)
    else:
        kp = np.asarray(keypoints, dtype=float)
    if kp.ndim != 2 or kp.shape[1] != 3 or not np.all(np.isfinite(kp)):
        raise ValueError(f"object '{object_id}': keypoints must be a finite (K, 3) array in metres, got {kp.shape}")
    faces = np.asarray(getattr(geometry, "faces", np.zeros((0, 3))), dtype=np.int64).reshape(-1, 3)
    info = _models_info(model_path)
    return ObjectModel(object_id, model_path, vertices, kp.astype(float), corners, _diameter_m(vertices, info), faces,
                       bop.symmetry_transforms(info or {}))


def load_object_folder(folder: str | Path) -> list[ObjectModel]:
    """Every BOP model of a folder (obj_NNNNNN.ply, in mm, with models_info.json beside them), each under its
    file stem (obj_000006). ValueError, naming the folder or file, when there is none, models_info.json is
    missing or does not list one, or a mesh does not load or has no faces (the estimators draw its outline)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder (a BOP models folder: obj_NNNNNN.ply with models_info.json)")
    paths = sorted(p for p in folder.glob("obj_*.ply") if BOP_MODEL.fullmatch(p.stem))
    if not paths:
        raise ValueError(f"{folder}: no BOP models (obj_NNNNNN.ply, in mm, with models_info.json beside them)")
    if not (folder / "models_info.json").is_file():
        raise ValueError(f"{folder}: no models_info.json beside the models (BOP's: diameters and symmetries, in mm)")
    models = []
    for path in paths:
        if _models_info(path) is None:
            raise ValueError(f"{path.name}: not listed in {folder / 'models_info.json'}")
        model = load_object(path.stem, path)
        if len(model.faces) == 0:
            raise ValueError(f"object '{model.object_id}': model {path} has no faces (a point cloud, not a mesh)")
        models.append(model)
    return models


def load_object_folders(folders: list[Path]) -> list[ObjectModel]:
    """The models of every folder (load_object_folder), in order, each id once; ValueError when two files
    claim one id."""
    models, seen = [], ObjectRegistry()
    for folder in folders:
        for model in load_object_folder(folder):
            if model.object_id not in seen:
                models.append(model)
            seen.add(model)  # the same id from two files: ValueError naming both
    return models


class ObjectRegistry:
    """The objects a server knows, by id."""

    def __init__(self, models: list[ObjectModel] | tuple[ObjectModel, ...] = ()):
        self._models = {m.object_id: m for m in models}

    def add(self, model: ObjectModel) -> None:
        """ValueError when another model holds the id already: two meshes under one id would be ambiguous."""
        known = self._models.get(model.object_id)
        if known is not None and known.model_path != model.model_path:
            raise ValueError(f"object '{model.object_id}' is registered twice: {known.model_path} and "
                             f"{model.model_path}")
        self._models[model.object_id] = model

    def get(self, object_id: str) -> ObjectModel:
        try:
            return self._models[object_id]
        except KeyError:
            raise UnknownObject(f"unknown object '{object_id}'; known: {self.ids()}") from None

    def ids(self) -> list[str]:
        return sorted(self._models)

    def __contains__(self, object_id: str) -> bool:
        return object_id in self._models

    @classmethod
    def from_config(cls, tables: dict, base_dir: Path) -> ObjectRegistry:
        """`tables` is the config's [objects] table: id -> {model, keypoints?, keypoint_count?}."""
        registry = cls()
        for object_id, table in tables.items():
            unknown = set(table) - {"model", "keypoints", "keypoint_count"}
            if unknown or "model" not in table:
                raise ValueError(f"[objects.{object_id}] needs `model` and accepts `keypoints`, `keypoint_count`; "
                                 f"got {sorted(table)}")
            keypoints = table.get("keypoints")
            if isinstance(keypoints, str):
                keypoints = resolve(keypoints, base_dir)
            registry.add(load_object(object_id, resolve(table["model"], base_dir), keypoints,
                                     int(table.get("keypoint_count", DEFAULT_KEYPOINT_COUNT))))
        return registry
