"""A sequence folder as one object: load it (synthetic or converted real data) or write it.

Frames are identified by integer ids; `frame_times.csv` gives each id's capture time in ns.
`rig.yaml` holds what neither BOP nor EuRoC has a file for: the camera-to-IMU extrinsic T_BC,
the object's world pose T_WO, the object id and the frame size.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from flextrack.formats import bop, euroc, kalibr
from flextrack.geometry.camera import PinholeCamera

FRAME_TIMES_HEADER = "#frame_id,timestamp [ns]"


@dataclass
class Sequence:
    root: Path
    imu: euroc.ImuData
    imu_noise: kalibr.ImuNoise
    frame_ids: np.ndarray  # (F,) int
    frame_times_ns: np.ndarray  # (F,) int64, sorted
    gt_T_CO: dict[int, np.ndarray]  # frame id -> T_CO (m)
    camera: PinholeCamera
    T_BC: np.ndarray  # camera -> IMU body
    T_WO: np.ndarray  # object -> world
    object_id: str
    bop_obj_id: int
    model_path: Path
    groundtruth: euroc.GroundTruth | None = None
    meta: dict = field(default_factory=dict)  # generator settings and statistics

    @property
    def name(self) -> str:
        return self.root.name

    def gt_times_and_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """Sorted capture times (ns) and (F, 4, 4) ground-truth T_CO for frames that have one."""
        keep = [i for i, f in enumerate(self.frame_ids) if int(f) in self.gt_T_CO]
        times = self.frame_times_ns[keep]
        poses = np.stack([self.gt_T_CO[int(self.frame_ids[i])] for i in keep]) if keep else np.zeros((0, 4, 4))
        return times, poses

    def rgb_path(self, frame_id: int) -> Path:
        return self.root / "rgb" / f"{frame_id:06d}.png"


def read_frame_times(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    rows = [line.split(",") for line in Path(path).read_text().splitlines() if line and not line.startswith("#")]
    ids = np.asarray([int(r[0]) for r in rows], dtype=np.int64)
    times = np.asarray([int(r[1]) for r in rows], dtype=np.int64)
    order = np.argsort(times, kind="stable")
    return ids[order], times[order]


def write_frame_times(path: str | Path, ids: np.ndarray, times_ns: np.ndarray) -> None:
    with open(path, "w") as f:
        f.write(FRAME_TIMES_HEADER + "\n")
        f.writelines(f"{int(i)},{int(t)}\n" for i, t in zip(ids, times_ns))


def load(root: str | Path) -> Sequence:
    """Read a sequence folder; raises FileNotFoundError naming the missing part, ValueError for a rig.yaml that
    is not a mapping of YAML."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"sequence folder {root} does not exist")
    if not (root / "rig.yaml").is_file():
        raise FileNotFoundError(f"{root}: not a sequence folder (no rig.yaml); make one with `flextrack simulate` "
                                "or `flextrack convert-euroc`")
    try:
        rig = yaml.safe_load((root / "rig.yaml").read_text())
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        raise ValueError(f"{root / 'rig.yaml'}: not valid YAML"
                         + (f" (line {where.line + 1})" if where is not None else "")) from None
    if not isinstance(rig, dict):
        raise ValueError(f"{root / 'rig.yaml'}: expected a mapping of keys (T_BC, T_WO, width, ...), "  # noqa: TRY004 (a file, not an argument)
                         f"got {type(rig).__name__}")
    noise, _ = kalibr.read_imu_sensor(root / "imu0" / "sensor.yaml")
    ids, times = read_frame_times(root / "frame_times.csv")
    bop_obj_id = int(rig["bop_obj_id"])
    Ks = bop.read_scene_camera(root / "scene_camera.json")
    K = next(iter(Ks.values()))
    camera = PinholeCamera.from_K(K, rig["width"], rig["height"], rig.get("distortion", ()))
    gt_path = root / "groundtruth.csv"
    meta_path = root / "sequence.yaml"
    return Sequence(
        root=root,
        imu=euroc.read_imu(root / "imu0" / "data.csv"),
        imu_noise=noise,
        frame_ids=ids,
        frame_times_ns=times,
        gt_T_CO=bop.read_scene_gt(root / "scene_gt.json", bop_obj_id),
        camera=camera,
        T_BC=np.asarray(rig["T_BC"], dtype=float),
        T_WO=np.asarray(rig["T_WO"], dtype=float),
        object_id=str(rig["object_id"]),
        bop_obj_id=bop_obj_id,
        model_path=root / rig["model"],
        groundtruth=euroc.read_groundtruth(gt_path) if gt_path.exists() else None,
        meta=yaml.safe_load(meta_path.read_text()) if meta_path.exists() else {},
    )


def save(seq: Sequence) -> None:
    """Write every part of `seq` under seq.root (the model file must already be there)."""
    root = seq.root
    (root / "imu0").mkdir(parents=True, exist_ok=True)
    euroc.write_imu(root / "imu0" / "data.csv", seq.imu)
    kalibr.write_imu_sensor(root / "imu0" / "sensor.yaml", seq.imu_noise, np.eye(4),
                            comment="IMU of a flextrack sequence (the IMU is the body frame B)")
    write_frame_times(root / "frame_times.csv", seq.frame_ids, seq.frame_times_ns)
    bop.write_scene_camera(root / "scene_camera.json", {int(i): seq.camera.K for i in seq.frame_ids})
    bop.write_scene_gt(root / "scene_gt.json", seq.gt_T_CO, seq.bop_obj_id)
    if seq.groundtruth is not None:
        euroc.write_groundtruth(root / "groundtruth.csv", seq.groundtruth)
    rig = {
        "object_id": seq.object_id,
        "bop_obj_id": seq.bop_obj_id,
        "model": str(seq.model_path.relative_to(root)) if seq.model_path.is_relative_to(root) else str(seq.model_path),
        "width": seq.camera.width,
        "height": seq.camera.height,
        "distortion": list(seq.camera.distortion),
        "T_BC": np.asarray(seq.T_BC).tolist(),
        "T_WO": np.asarray(seq.T_WO).tolist(),
    }
    (root / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
    if seq.meta:
        (root / "sequence.yaml").write_text(yaml.safe_dump(seq.meta, sort_keys=False))
