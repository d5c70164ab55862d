"""Real data in: a EuRoC recording (real IMU, Vicon ground truth, cam0 calibration) as a sequence folder.

The IMU and the ground truth are copied unchanged; the camera is EuRoC's cam0 (752x480, radtan
distortion, T_BS of cam0 is our T_BC). There are no images of an object, so a virtual object is
placed in the Vicon world where cam0 sees it for as much of the run as possible: candidate points
are put on the optical axes of the frames at several depths, and the one seen whole, and large
enough for the PIA (its image box >= frame area / 100, with a margin), in the most frames wins.
The object may be scaled (`object_scale`: a scaled copy of the BOP model, mm, is written into the
sequence's models/): the MAV flies 1-4 m from anything, where a 15 cm object is far below the
PIA's area limit in cam0. The object stands upright (world z is up in EuRoC's Vicon frame) and
faces the cameras.

Frames are at cam0's 20 Hz or any rate asked, from `IMU_LEAD_S` after the IMU's first sample: the
MAV recordings begin with ~0.7 s of stillness, and the tracker initialises gravity and gyro bias
from the 0.5 s of still IMU before its first frame (the paper's "System Initialization"). The
Vicon ground truth of V1_02 starts ~1 s after the IMU, when the MAV already moves; the poses of
the frames before it come from the first ground-truth state: orientation integrated backwards
through the gyro, position extrapolated at the recorded velocity (`_backfill`; the MAV moves at
~1 cm/s then, so < 5 mm over the ~0.45 s). Camera poses are the body poses interpolated at the frame times and moved
to cam0 by T_BC.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flextrack import assets
from flextrack.formats import euroc, kalibr
from flextrack.formats.sequence import Sequence
from flextrack.geometry import se3, so3
from flextrack.geometry.camera import PinholeCamera
from flextrack.runners.exchange import FRAME_LATENCY_KEY
from flextrack.simulator import default_object
from flextrack.simulator.render import load_model
from flextrack.simulator.sequence_writer import bop_obj_id_of, install_model, write_sequence

MIN_DISTANCE_M, MAX_DISTANCE_M = 0.6, 3.0
IMU_LEAD_S = 0.55  # the first frame comes this long after the IMU starts: 0.5 s still window + margin
OBJECT_SCALE = 4.0  # default: the 15 cm default object becomes a 58 cm box, which PIA accepts to ~2.2 m in cam0
PLACEMENT_RATE_HZ = 20.0  # the camera poses the placement looks at (independent of the frame rate)
AREA_MARGIN = 1.3  # placement counts a frame as seen when the object's image box is >= 1.3 x THR_area


@dataclass
class Placement:
    centre_W: np.ndarray  # the object's centre in the world
    visible_fraction: float  # frames that see the whole object at MIN..MAX distance
    distance_m: tuple[float, float, float]  # min, median, max over the frames that see it


def visibility(points_W: np.ndarray, T_WC: np.ndarray, camera: PinholeCamera, radius_m: float,
               max_distance_m: float = MAX_DISTANCE_M) -> np.ndarray:
    """(P, F) bool: point p is in front of frame f's camera at MIN_DISTANCE_M..max_distance_m, with
    a disc of `radius_m` around it inside the image."""
    T_CW = np.linalg.inv(T_WC)
    pc = np.einsum("fij,pj->pfi", T_CW[:, :3, :3], points_W) + T_CW[None, :, :3, 3]
    z = pc[..., 2]
    safe_z = np.where(z > 1e-6, z, 1e-6)
    u = camera.fx * pc[..., 0] / safe_z + camera.cx
    v = camera.fy * pc[..., 1] / safe_z + camera.cy
    margin = camera.fx * radius_m / safe_z
    dist = np.linalg.norm(pc, axis=-1)
    return ((z > 0) & (dist >= MIN_DISTANCE_M) & (dist <= max_distance_m)
            & (u - margin >= 0) & (u + margin <= camera.width - 1)
            & (v - margin >= 0) & (v + margin <= camera.height - 1))


def pia_distance_m(camera: PinholeCamera, box_size_m: np.ndarray, area_divisor: float = 100.0) -> float:
    """Farthest distance at which the object's image box still covers AREA_MARGIN x frame area /
    `area_divisor` seen along its least favourable side (the two smallest box edges)."""
    a, b = np.sort(np.asarray(box_size_m, float))[:2]
    thr = AREA_MARGIN * camera.width * camera.height / area_divisor
    return float(np.sqrt(camera.fx * camera.fy * a * b / thr))


def place_object(T_WC: np.ndarray, camera: PinholeCamera, radius_m: float,
                 max_distance_m: float = MAX_DISTANCE_M, distance_m: float | None = None,
                 position_W: np.ndarray | None = None) -> Placement:
    """The candidate point (on the optical axes of ~150 frames, at 5 depths, or at `distance_m` alone) seen
    whole in the most frames; or `position_W` as given, with its visibility."""
    every = max(1, len(T_WC) // 150)
    origins, axes = T_WC[::every, :3, 3], T_WC[::every, :3, 2]
    depths = np.linspace(MIN_DISTANCE_M, max_distance_m, 7)[1:-1] if distance_m is None else np.array([distance_m])
    candidates = (origins[:, None] + depths[None, :, None] * axes[:, None]).reshape(-1, 3)
    if position_W is not None:
        candidates = np.asarray(position_W, float).reshape(1, 3)
    seen = visibility(candidates, T_WC, camera, radius_m, max_distance_m)
    score = seen.mean(axis=1)
    best = int(np.argmax(score))
    dist = np.linalg.norm(T_WC[seen[best], :3, 3] - candidates[best], axis=1)
    stats = (float(dist.min()), float(np.median(dist)), float(dist.max())) if len(dist) else (0.0, 0.0, 0.0)
    return Placement(candidates[best], float(score[best]), stats)


def convert_euroc(euroc_dir: str | Path, out_dir: str | Path, *, fps: float | None = None,
                  object_path: str | Path | None = None, object_id: str | None = None,
                  max_distance_m: float = MAX_DISTANCE_M, object_scale: float = OBJECT_SCALE,
                  object_position: tuple[float, float, float] | None = None,
                  object_distance_m: float | None = None, frame_latency_ms: float | None = None) -> Path:
    """Write the sequence folder `out_dir` from a EuRoC folder holding imu0.csv, groundtruth.csv,
    cam0_sensor.yaml and imu0_sensor.yaml (or the mav0/ layout: imu0/data.csv, ...). The object goes where
    `place_object` finds the cameras look most (at `object_distance_m` from them when given), or at
    `object_position` (world, m) when given; `frame_latency_ms`, when given, is declared for the replay
    (`runners.exchange.FRAME_LATENCY_KEY`; undeclared, a phone's default)."""
    src = Path(euroc_dir)
    paths = _find_files(src)
    imu = euroc.read_imu(paths["imu"])
    gt = euroc.read_groundtruth(paths["gt"])
    noise, _ = kalibr.read_imu_sensor(paths["imu_yaml"])
    cam = kalibr.read_camera_sensor(paths["cam_yaml"])
    camera = PinholeCamera.from_K(cam.K, cam.width, cam.height, tuple(float(x) for x in cam.distortion))
    fps = float(fps or cam.rate_hz)
    if fps <= 0:
        raise ValueError("fps must be positive")
    if not max_distance_m > MIN_DISTANCE_M:
        raise ValueError(f"the object's maximum distance must exceed {MIN_DISTANCE_M} m")
    if not (np.isfinite(object_scale) and object_scale > 0):
        raise ValueError(f"object_scale must be a positive number, got {object_scale!r}")

    first = int(imu.t_ns[0]) + int(IMU_LEAD_S * 1e9)
    last = min(int(gt.t_ns[-1]), int(imu.t_ns[-1]))
    if last <= max(first, int(gt.t_ns[0])):
        raise ValueError(f"{src}: the IMU and the ground truth do not overlap")
    frame_t = np.arange(first, last + 1, round(1e9 / fps), dtype=np.int64)
    gt_t, gt_poses = _backfill(gt, imu, min(first, int(gt.t_ns[0])))
    T_WB = np.stack([se3.interpolate_at(gt_t, gt_poses, int(t)) for t in frame_t])
    T_WC = T_WB @ cam.T_BS

    source = Path(object_path) if object_path is not None else assets.default_object_model()
    if object_id is None:
        object_id = default_object.OBJECT_ID if object_path is None else source.stem
    bop_obj_id = default_object.BOP_OBJ_ID if object_path is None else bop_obj_id_of(source)
    root = Path(out_dir)
    model = install_model(source, root, bop_obj_id) if object_scale == 1.0 else \
        install_scaled_model(source, root, bop_obj_id, object_scale)
    vertices = np.asarray(load_model(model).vertices)
    centre_O = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    pia_reach_m = pia_distance_m(camera, vertices.max(axis=0) - vertices.min(axis=0))
    reach_m = min(max_distance_m, pia_reach_m)
    if not reach_m > MIN_DISTANCE_M:
        raise ValueError(f"the object (scale {object_scale:g}) is too small for the PIA in this camera beyond "
                         f"{pia_reach_m:.2f} m, below the {MIN_DISTANCE_M} m minimum: use an object scale of at "
                         f"least {object_scale * 1.5 * MIN_DISTANCE_M / pia_reach_m:.1f}")
    if object_distance_m is not None and not MIN_DISTANCE_M <= object_distance_m <= reach_m:
        raise ValueError(f"the object distance must be within {MIN_DISTANCE_M}..{reach_m:.2f} m (where the PIA "
                         f"still accepts the object at scale {object_scale:g}), got {object_distance_m:g}")
    # placed from the camera's path at a fixed rate, not at the frames': the object stays where it is at any --fps
    place_t = np.arange(first, last + 1, round(1e9 / PLACEMENT_RATE_HZ), dtype=np.int64)
    T_WC_place = np.stack([se3.interpolate_at(gt_t, gt_poses, int(t)) for t in place_t]) @ cam.T_BS
    placement = place_object(T_WC_place, camera, float(np.linalg.norm(vertices - centre_O, axis=1).max()), reach_m,
                             distance_m=object_distance_m, position_W=object_position)
    facing = np.median(T_WC_place[:, :3, 3], axis=0) - placement.centre_W  # turn the object's +x to the cameras
    R_WO = so3.exp(np.array([0.0, 0.0, np.arctan2(facing[1], facing[0])]))
    T_WO = se3.make(R_WO, placement.centre_W - R_WO @ centre_O)
    T_CW = np.linalg.inv(T_WC)
    ids = np.arange(len(frame_t))
    seq = Sequence(
        root=root, imu=imu, imu_noise=noise, frame_ids=ids, frame_times_ns=frame_t,
        gt_T_CO={int(i): T_CW[i] @ T_WO for i in ids}, camera=camera, T_BC=cam.T_BS, T_WO=T_WO,
        object_id=object_id, bop_obj_id=bop_obj_id, model_path=model, groundtruth=gt,
        meta={
            "converter": {"source": str(src.resolve()), "source_name": _source_name(src),
                          "imu": imu_label(paths["imu_yaml"]), "fps": fps, "object": str(object_path or "default"),
                          "object_scale": float(object_scale), "imu_lead_s": IMU_LEAD_S,
                          "max_distance_m": max_distance_m, "placement_distance_m": reach_m,
                          "groundtruth_backfilled_s": max(0.0, (int(gt.t_ns[0]) - first) * 1e-9)},
            "placement": {"how": "given" if object_position is not None else
                          ("auto" if object_distance_m is None else f"auto at {object_distance_m:g} m"),
                          "centre_W": placement.centre_W.tolist(), "visible_fraction": placement.visible_fraction,
                          "distance_m_min_median_max": list(placement.distance_m)},
            "times_ns": {"imu_start": int(imu.t_ns[0]), "end": int(last)},
            **({} if frame_latency_ms is None else {FRAME_LATENCY_KEY: float(frame_latency_ms)}),
        },
    )
    write_sequence(seq)
    return root


def imu_label(sensor_yaml: Path) -> str:
    """A name for the IMU from its Kalibr yaml: its `comment` (EuRoC: 'VI-Sensor IMU (ADIS16448)') or its rate."""
    data = kalibr._load_yaml(sensor_yaml) or {}
    comment = str(data.get("comment", "")).strip()
    rate = data.get("rate_hz") or data.get("update_rate")
    return comment or (f"IMU at {float(rate):g} Hz" if rate else "IMU")


def _source_name(src: Path) -> str:
    """The recording's name: its folder's, or the parent's for EuRoC's mav0/ folder."""
    src = src.resolve()
    return src.parent.name if src.name == "mav0" else src.name


def install_scaled_model(source: Path, root: Path, bop_obj_id: int, scale: float) -> Path:
    """Write root/models/obj_<id>.ply, the model scaled by `scale` (mm, colours kept), with its
    models_info.json."""
    import trimesh

    from flextrack.formats import bop
    from flextrack.simulator.sequence_writer import models_info

    if not Path(source).is_file():
        raise FileNotFoundError(f"object model {source} does not exist")
    mesh = trimesh.load(source, process=False, force="mesh")
    mesh.apply_scale(scale)
    models = root / "models"
    models.mkdir(parents=True, exist_ok=True)
    dst = models / f"obj_{bop_obj_id:06d}.ply"
    mesh.export(dst, encoding="binary")
    bop.write_models_info(models / "models_info.json", {bop_obj_id: models_info(np.asarray(mesh.vertices))})
    return dst


def _backfill(gt: euroc.GroundTruth, imu: euroc.ImuData, t_from_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth times and T_WB from `t_from_ns`: the recorded ones, preceded (when the IMU starts
    before the ground truth) by poses at the IMU's sample times back from the first recorded state:
    the orientation integrated backwards through the gyro (less the ground truth's gyro bias), the
    position extrapolated at the first recorded velocity. Not the accelerometer: in EuRoC's first
    second the rotors spin up, and double-integrating their vibration drifts ~5 cm in 0.5 s while
    the MAV moves at ~1 cm/s."""
    poses = np.stack([se3.from_quat_translation(q, p) for q, p in zip(gt.q_WB, gt.p_WB)])
    times = np.asarray(gt.t_ns, dtype=np.int64)
    back = np.flatnonzero((imu.t_ns >= t_from_ns) & (imu.t_ns < times[0]))
    if not len(back):
        return times, poses
    R, p0, v0 = poses[0][:3, :3].copy(), poses[0][:3, 3], np.asarray(gt.v_WB[0], float)
    b_g = np.asarray(gt.bias_gyro[0], float)
    t = int(times[0])
    out_t, out_T = [], []
    for i in back[::-1]:  # newest first, stepping back from the first ground-truth state
        R = R @ so3.exp(-(imu.gyro[i] - b_g) * (t - int(imu.t_ns[i])) * 1e-9)
        t = int(imu.t_ns[i])
        out_t.append(t)
        out_T.append(se3.make(R, p0 - v0 * (int(times[0]) - t) * 1e-9))
    return np.concatenate([np.array(out_t[::-1], dtype=np.int64), times]), np.concatenate([np.stack(out_T[::-1]), poses])


def _find_files(src: Path) -> dict[str, Path]:
    """The four inputs, in the flat layout of shared/data or in EuRoC's mav0 layout."""
    layouts = [
        {"imu": "imu0.csv", "gt": "groundtruth.csv", "imu_yaml": "imu0_sensor.yaml", "cam_yaml": "cam0_sensor.yaml"},
        {"imu": "imu0/data.csv", "gt": "state_groundtruth_estimate0/data.csv", "imu_yaml": "imu0/sensor.yaml",
         "cam_yaml": "cam0/sensor.yaml"},
    ]
    for base in (src, src / "mav0"):
        for layout in layouts:
            paths = {k: base / v for k, v in layout.items()}
            if all(p.is_file() for p in paths.values()):
                return paths
    raise FileNotFoundError(f"{src} holds no EuRoC recording (need imu0.csv, groundtruth.csv, "
                            "imu0_sensor.yaml, cam0_sensor.yaml, or the mav0/ layout)")
