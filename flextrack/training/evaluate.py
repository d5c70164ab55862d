"""Evaluate a PVNet ONNX model through the `pvnet` estimator, as the server would run it.

Two kinds of frames:
- rendered (default): frames of the object standing on the table of the simulator's room, seen
  from random viewpoints above it at 0.45-1.5 m with the object anywhere in view; the rooms, the
  poses and the camera's placement are drawn from seeds training never used;
- `--bop SCENE_DIR --obj-id N`: real BOP frames (rgb/, scene_gt.json, scene_camera.json,
  scene_gt_info.json), split by the visible fraction of the object; or a simulated sequence's
  folder (BOP files too), whose frames with an image are scored as one group.

It reports, per group, the share of frames with mean 2D projection error below 5 px, with ADD and
with ADD-S (the symmetric-object metric, BOP's `adi`) below 10 % of the diameter, and ADD(-S), the
one of the two that fits the object (ADD-S when its models_info.json gives symmetries; BOP
definitions; a frame without a pose counts as a failure), writes
per-frame rows to results.json and draws the estimated pose (green: truth, red: estimate) over
the frames in a contact sheet.

    python -m flextrack.training.evaluate --model flextrack/assets/models/pvnet_default/pvnet.onnx --object default --out runs/eval
    python -m flextrack.training.evaluate --model runs/cat/pvnet.onnx --object .../obj_000006.ply \\
        --bop ../shared/data/lmo/test/000002 --obj-id 6 --out runs/eval_cat
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from flextrack.provenance import of_args
from flextrack.provenance import provenance as flextrack_provenance

PROJ_PX = 5.0
ADD_FRACTION = 0.1


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="PVNet ONNX file")
    parser.add_argument("--object", default="default", help="'default' or the BOP .ply (mm) the model was trained on")
    parser.add_argument("--out", required=True, type=Path, help="folder for results.json and the contact sheet")
    parser.add_argument("--frames", type=int, default=200, help="rendered frames")
    parser.add_argument("--seed", type=int, default=20261122, help="seed of the rendered frames (never a training seed)")
    parser.add_argument("--scenes", type=int, default=4, help="rooms the rendered frames are spread over")
    parser.add_argument("--roll-deg", type=float, default=0.0,
                        help="rendered frames: the camera turned this far about its optical axis (the same "
                             "viewpoints whatever the roll)")
    parser.add_argument("--bop", type=Path, help="evaluate on a BOP scene folder instead of rendered frames (also a "
                        "simulated sequence's folder: its frames with an image)")
    parser.add_argument("--obj-id", type=int, default=6, help="BOP object id in --bop's scene_gt.json")
    parser.add_argument("--no-zoom", action="store_true", help="vote on the whole-frame pass only (no crop pass)")
    parser.add_argument("--rotations", type=int, default=4, choices=(1, 4),
                        help="the estimator's crop turns (1: the crop only as it is)")
    parser.add_argument("--no-refine", action="store_true", help="keep PnP's pose (no refinement on the image's edges)")
    parser.add_argument("--sheet", type=int, default=20, help="frames drawn in the contact sheet")
    parser.add_argument("--jpeg", type=int, metavar="QUALITY",
                        help="send each frame through JPEG at this quality first, as the device does; without it "
                        "the frames are scored as rendered or read")
    parser.add_argument("--jpeg-chroma", choices=("444", "420"), default="444",
                        help="with --jpeg: full-resolution colour (the device's) or JPEG's usual halved colour")


# ---- frames -----------------------------------------------------------------------------------

def rendered_frames(model_path: Path, n: int, seed: int, scenes: int, roll_deg: float = 0.0):
    """Yields (name, rgb, camera, T_CO, group) for n frames in the simulator's room, the camera rolled
    by roll_deg about its optical axis (the same viewpoints whatever the roll)."""
    from flextrack.geometry import se3, so3
    from flextrack.geometry.camera import PinholeCamera
    from flextrack.simulator.render import Renderer, load_model
    from flextrack.simulator.scene import make_scene
    from flextrack.training.pvnet_data import look_at_pose

    camera = PinholeCamera.linemod()
    vertices = np.asarray(load_model(model_path).vertices)
    T_WO = se3.make(np.eye(3), [0.0, 0.0, -vertices[:, 2].min()])  # standing on the table top (z = 0)
    centre_W = se3.transform_points(T_WO, (vertices.min(axis=0) + vertices.max(axis=0))[None] / 2)[0]
    rng = np.random.default_rng(seed)
    roll = se3.make(so3.exp(np.array([0.0, 0.0, np.radians(roll_deg)])), np.zeros(3))
    per_scene = int(np.ceil(n / scenes))
    for s in range(scenes):
        with Renderer(camera, model_path, scene=make_scene(seed + s), T_WO=T_WO) as renderer:
            for i in range(s * per_scene, min(n, (s + 1) * per_scene)):
                T_CO = roll @ se3.inverse(look_at_pose(rng, camera, centre_W)) @ T_WO
                yield f"{i:04d}", renderer.render(T_CO).rgb, camera, T_CO, "rendered"


def as_sent(frames, quality: int, chroma: str):
    """The frames JPEG-encoded as the device sends them and decoded as the service does."""
    from flextrack.runners.payload import frame_jpeg
    from flextrack.v1 import pose_estimation_pb2 as pb
    from service.request_decoding import decode_image

    for name, rgb, camera, T_CO, group in frames:
        image = pb.Image(encoding=pb.Image.JPEG, data=frame_jpeg(rgb, quality, chroma), width=rgb.shape[1],
                         height=rgb.shape[0])
        yield name, decode_image(image, camera), camera, T_CO, group


def bop_frames(scene_dir: Path, obj_id: int):
    """Yields (name, rgb, camera, T_CO, group) for the frames of a BOP scene that have an image and show
    obj_id, grouped by visible fraction where the scene has scene_gt_info.json. A simulated sequence's
    folder (`flextrack simulate`, or the frames a table2 run sent) has images of the sent frames only
    and no scene_gt_info.json: its frames form one group, "all"."""
    from flextrack.formats import bop
    from flextrack.geometry.camera import PinholeCamera

    poses = bop.read_scene_gt(scene_dir / "scene_gt.json", obj_id)
    Ks = bop.read_scene_camera(scene_dir / "scene_camera.json")
    gt = json.loads((scene_dir / "scene_gt.json").read_text())
    info_path = scene_dir / "scene_gt_info.json"
    info = json.loads(info_path.read_text()) if info_path.is_file() else None
    for path in sorted((scene_dir / "rgb").glob("*.png")):
        frame = int(path.stem)
        if frame not in poses:
            continue
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise FileNotFoundError(f"cannot read {path}")
        group = "all"
        if info is not None:
            k = next(i for i, a in enumerate(gt[str(frame)]) if int(a["obj_id"]) == obj_id)
            group = "visib>0.8" if float(info[str(frame)][k]["visib_fract"]) > 0.8 else "visib<=0.8"
        camera = PinholeCamera.from_K(Ks[frame], bgr.shape[1], bgr.shape[0])
        yield f"{frame:06d}", cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), camera, poses[frame], group


# ---- evaluation -------------------------------------------------------------------------------

def draw_pose(rgb: np.ndarray, camera, T_gt: np.ndarray, T_est: np.ndarray | None, corners: np.ndarray,
              label: str) -> np.ndarray:
    """The object's 3D box under the true (green) and estimated (red) pose."""
    from flextrack.geometry.camera import project_model

    img = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    edges = [(0, 1), (0, 2), (0, 4), (1, 3), (1, 5), (2, 3), (2, 6), (3, 7), (4, 5), (4, 6), (5, 7), (6, 7)]
    for T, colour in ((T_gt, (0, 200, 0)), (T_est, (0, 0, 255))):
        if T is None or T[2, 3] <= 0:
            continue
        p = np.round(project_model(camera, T, corners)).astype(int)
        for a, b in edges:
            cv2.line(img, tuple(map(int, p[a])), tuple(map(int, p[b])), colour, 2, cv2.LINE_AA)
    cv2.putText(img, label, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 3, cv2.LINE_AA)
    cv2.putText(img, label, (8, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 0), 1, cv2.LINE_AA)
    return img


def contact_sheet(images: list[np.ndarray], columns: int = 5, width: int = 320) -> np.ndarray:
    tiles = [cv2.resize(im, (width, int(im.shape[0] * width / im.shape[1])), interpolation=cv2.INTER_AREA)
             for im in images]
    while len(tiles) % columns:
        tiles.append(np.zeros_like(tiles[0]))
    return np.vstack([np.hstack(tiles[r:r + columns]) for r in range(0, len(tiles), columns)])


def summarise(rows: list[dict]) -> dict:
    groups: dict[str, list[dict]] = {}
    for row in rows:
        groups.setdefault(row["group"], []).append(row)
    summary = {}
    for name, rs in sorted(groups.items()):
        proj = np.array([r["proj_px"] for r in rs])
        add_ok, adds_ok = np.array([r["add_ok"] for r in rs]), np.array([r["adds_ok"] for r in rs])
        symmetric = bool(rs[0]["symmetric"])
        summary[name] = {"frames": len(rs), "found": int(sum(r["status"] == "OK" for r in rs)),
                         "proj_below_5px": float(np.mean(proj < PROJ_PX)),
                         "add_below_10pct": float(np.mean(add_ok)),
                         "adds_below_10pct": float(np.mean(adds_ok)),
                         "symmetric": symmetric,  # ADD(-S): ADD-S for a symmetric object, ADD otherwise
                         "add_s_below_10pct": float(np.mean(adds_ok if symmetric else add_ok)),
                         "median_proj_px": float(np.median(proj))}
    return summary


def evaluate(model: Path, object_path: Path, frames, out: Path, zoom: bool = True, sheet: int = 20,
             rotations: int = 4, refine: bool = True, jpeg: str | None = None, provenance: dict | None = None) -> dict:
    """Scores `frames` with the pvnet estimator; writes results.json (with `provenance`, by default these
    arguments' own) and the pose pictures. `jpeg`: how the frames were encoded first (e.g. "90/444")."""
    from estimators.base import EstimateInput, Status
    from estimators.objects import ObjectRegistry, load_object
    from estimators.pvnet import PvnetEstimator
    from flextrack.geometry import metrics

    obj = load_object("object", object_path)
    estimator = PvnetEstimator(ObjectRegistry([obj]), model, zoom=zoom, rotations=rotations, refine=refine)
    adds_of = metrics.AddS(obj.vertices)  # one KD-tree of the mesh for every frame
    symmetric = len(obj.symmetries) > 1
    rows, drawings = [], []
    out.mkdir(parents=True, exist_ok=True)
    for i, (name, rgb, camera, T_gt, group) in enumerate(frames):
        result = estimator.estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=camera, image=rgb))
        T_est = result.T_CO if result.status == Status.OK else None
        proj = metrics.proj_px(T_est, T_gt, camera, obj.vertices) if T_est is not None else float("inf")
        add = metrics.add_m(T_est, T_gt, obj.vertices) if T_est is not None else float("inf")
        adds = adds_of(T_est, T_gt) if T_est is not None else float("inf")
        rows.append({"frame": name, "group": group, "status": result.status.value, "proj_px": proj,
                     "add_mm": add * 1e3, "add_ok": bool(add < ADD_FRACTION * obj.diameter_m),
                     "adds_mm": adds * 1e3, "adds_ok": bool(adds < ADD_FRACTION * obj.diameter_m),
                     "symmetric": symmetric,
                     "te_mm": metrics.te_mm(T_est, T_gt) if T_est is not None else None,
                     "re_deg": metrics.re_deg(T_est, T_gt) if T_est is not None else None,
                     "confidence": result.confidence, "stage_ms": result.stage_ms})
        if len(drawings) < sheet:
            drawings.append(draw_pose(rgb, camera, T_gt, T_est, obj.bbox_corners,
                                      f"{name} {group} proj {proj:.1f}px"))
    summary = summarise(rows)
    (out / "results.json").write_text(json.dumps({"model": str(model), "object": str(object_path), "zoom": zoom,
                                                  "rotations": rotations, "refine": refine, "jpeg": jpeg, "summary": summary,
                                                  "provenance": provenance or flextrack_provenance(
                                                      model=str(model), object=str(object_path), zoom=zoom,
                                                      rotations=rotations, refine=refine, jpeg=jpeg),
                                                  "frames": rows}, indent=1))
    if drawings:
        cv2.imwrite(str(out / "poses.jpg"), contact_sheet(drawings), [cv2.IMWRITE_JPEG_QUALITY, 85])
    return summary


def run(args) -> int:
    from flextrack.assets import object_model

    try:
        object_path = object_model(args.object)
        if not args.model.is_file():
            raise FileNotFoundError(f"model {args.model} not found")
        if args.bop is not None:
            if not (args.bop / "scene_gt.json").is_file():
                raise FileNotFoundError(f"{args.bop} is not a BOP scene folder (no scene_gt.json)")
            frames = bop_frames(args.bop, args.obj_id)
        else:
            frames = rendered_frames(object_path, args.frames, args.seed, args.scenes, args.roll_deg)
        if args.jpeg is not None:
            frames = as_sent(frames, args.jpeg, args.jpeg_chroma)
        provenance = of_args(args, command="flextrack train pvnet-eval")
        if args.bop is not None and (args.bop / "sequence.yaml").is_file():  # a simulated sequence: how it was made
            import yaml

            provenance["frames_generator"] = yaml.safe_load((args.bop / "sequence.yaml").read_text()).get("generator")
        summary = evaluate(args.model, object_path, frames, args.out, zoom=not args.no_zoom, sheet=args.sheet,
                           rotations=args.rotations, refine=not args.no_refine,
                           jpeg=None if args.jpeg is None else f"{args.jpeg}/{args.jpeg_chroma}",
                           provenance=provenance)
    except (FileNotFoundError, ValueError) as exc:
        print(f"flextrack train pvnet-eval: {exc}", file=sys.stderr)
        return 2
    for group, s in summary.items():
        print(f"{group:>12}: {s['frames']} frames, pose found {s['found']}, proj < 5 px {100 * s['proj_below_5px']:.1f} %, "
              f"< 10 % diameter: ADD {100 * s['add_below_10pct']:.1f} %, ADD-S {100 * s['adds_below_10pct']:.1f} %, "
              f"ADD(-S) {100 * s['add_s_below_10pct']:.1f} % ({'ADD-S: symmetric' if s['symmetric'] else 'ADD: no symmetry'}"
              f" in models_info.json), median proj {s['median_proj_px']:.2f} px")
    print(f"per-frame results: {args.out / 'results.json'}; poses drawn: {args.out / 'poses.jpg'}")
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    add_arguments(parser)
    sys.exit(run(parser.parse_args()))
