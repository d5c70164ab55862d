"""`flextrack evaluate prior`: score an estimator on a BOP folder with priors drawn around the
ground truth.

For every object instance of the folder (one object, a list, or `all` of its models), and every prior
level (per-axis sigmas in mm and degrees, or `none`), `draws` priors are drawn (seeded): e = (d_theta,
d_t) ~ N(0, diag(sigma_r^2, sigma_t^2)) in the wire convention (flextrack.wire: R_true = Exp(d_theta)
R_prior, t_true = t_prior + d_t), sent with that diagonal covariance; `--flip` then turns each prior
180 deg about the camera's ray through the object (a badly wrong prior that claims to be tight).
Reported per level, overall, per object and per visibility band (BOP's `visib_fract`): the share of
answers under 5 px of 2D projection error (BOP's proj over the model's vertices, the smallest over the
object's symmetries), the share under ADD(-S) 10 % of the diameter (ADD-S for objects with symmetries),
the median 2D error (a failure counts as infinitely far), the share answered OK yet more than 20 px
off (confident and wrong), the same for the priors themselves, the time per estimate and the NEES of
the answers' covariances (against the nearest symmetric pose); per answer, also where it puts the object's
centre in the image against the truth (`centre_offset_px`: a lean shows there). Draw d of every level runs as one
session per object through the frames in order (the colour histograms carry over, as on a device),
unless `--fresh` starts every instance afresh. `--part even|odd` keeps every other frame of each
scene, so that settings tuned on one half are scored on the other. `--colours-at-truth` is an oracle: region's
fits learn their first colours at the true outline (flextrack.evaluation.colours_at_truth), which says what
region's colour model costs it.

The estimator is any [[estimators]] entry of a service config, rebound to the folder's object: its
`objects` (and those of the entries it names) become the BOP object. An entry that cannot be built
for that object (pvnet's network knows only the default object) is reported as such.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from flextrack.formats import bop
from flextrack.geometry import metrics, se3, so3
from flextrack.geometry.camera import PinholeCamera, project_model
from flextrack.provenance import command_line, provenance

DEFAULT_LEVELS = "10:5,20:10,none"


VISIB_BANDS = ((0.0, 0.3), (0.3, 0.5), (0.5, 0.8), (0.8, 1.01))  # BOP visib_fract, [lo, hi)
WRONG_PX = 20.0  # an OK answer further off than this is "confident and wrong"


@dataclass(frozen=True)
class Frame:
    """One object instance in one frame (the name stays from when a frame showed one object)."""

    scene: int
    frame_id: int
    rgb_path: Path
    K: np.ndarray
    T_gt: np.ndarray
    obj_id: int = 0
    visib: float | None = None  # BOP's visib_fract, where scene_gt_info.json gives it
    instance: int = 0  # the instance's index in the frame's scene_gt list


@dataclass(frozen=True)
class PriorLevel:
    sigma_mm: float | None  # None: no prior
    sigma_deg: float | None

    @property
    def label(self) -> str:
        return "none" if self.sigma_mm is None else f"{self.sigma_mm:g}mm/{self.sigma_deg:g}deg"

    @property
    def seed_key(self) -> tuple[int, int]:
        """The level's part of its draws' seed: its sigmas in micrometres and millidegrees."""
        return (0, 0) if self.sigma_mm is None else (round(self.sigma_mm * 1000), round(self.sigma_deg * 1000))

    @property
    def covariance(self) -> np.ndarray:
        return np.diag([np.radians(self.sigma_deg) ** 2] * 3 + [(self.sigma_mm / 1000.0) ** 2] * 3)


def parse_levels(text: str) -> list[PriorLevel]:
    """'10:5,20:10,none' -> levels (mm:deg per axis, or none)."""
    levels = []
    for part in text.split(","):
        part = part.strip()
        if part == "none":
            levels.append(PriorLevel(None, None))
        else:
            mm, _, deg = part.partition(":")
            levels.append(PriorLevel(float(mm), float(deg)))
    return levels


def bop_frames(folder: Path, obj_id: int, split: str = "test", limit: int | None = None) -> list[Frame]:
    """Frames of every scene under folder/split that annotate obj_id, in scene and frame order."""
    frames = bop_instances(folder, [obj_id], split)
    return frames[:limit] if limit else frames


def bop_instances(folder: Path, obj_ids: list[int], split: str = "test", part: str = "all",
                  min_visib: float = 0.0) -> list[Frame]:
    """Every instance of the objects in every scene under folder/split, in scene, frame and instance order;
    `part` "even" / "odd" keeps every other frame of a scene (by its sorted ids), "all" all of them;
    instances less visible than `min_visib` left out (instances without visibility kept)."""
    wanted = set(obj_ids)
    out = []
    for scene_dir in sorted(p for p in (folder / split).iterdir() if p.is_dir()):
        gt_doc = json.loads((scene_dir / "scene_gt.json").read_text())
        info_path = scene_dir / "scene_gt_info.json"
        info_doc = json.loads(info_path.read_text()) if info_path.is_file() else {}
        Ks = bop.read_scene_camera(scene_dir / "scene_camera.json")
        frame_ids = sorted(int(k) for k in gt_doc)
        if part != "all":
            frame_ids = frame_ids[(0 if part == "even" else 1)::2]
        for frame_id in frame_ids:
            rgb = next((scene_dir / "rgb" / f"{frame_id:06d}{ext}" for ext in (".png", ".jpg")
                        if (scene_dir / "rgb" / f"{frame_id:06d}{ext}").is_file()), None)
            if rgb is None:
                continue
            infos = info_doc.get(str(frame_id), [])
            for k, entry in enumerate(gt_doc[str(frame_id)]):
                if int(entry["obj_id"]) not in wanted:
                    continue
                visib = float(infos[k]["visib_fract"]) if k < len(infos) and "visib_fract" in infos[k] else None
                if visib is not None and visib < min_visib:
                    continue
                T = np.eye(4)
                T[:3, :3] = np.asarray(entry["cam_R_m2c"], float).reshape(3, 3)
                T[:3, 3] = np.asarray(entry["cam_t_m2c"], float) / 1000.0
                out.append(Frame(int(scene_dir.name), frame_id, rgb, Ks[frame_id], T, int(entry["obj_id"]), visib, k))
    return out


def visib_band(visib: float | None) -> str:
    if visib is None:
        return "unknown"
    lo, hi = next(b for b in VISIB_BANDS if b[0] <= visib < b[1] or b == VISIB_BANDS[-1])
    return f"{lo:g}-{min(hi, 1.0):g}"


def perturb(T: np.ndarray, level: PriorLevel, rng: np.random.Generator) -> np.ndarray:
    """A prior T_prior with T = (Exp(d_theta) R_prior, t_prior + d_t), e drawn at the level's sigmas."""
    d_theta = rng.normal(0.0, np.radians(level.sigma_deg), 3)
    d_t = rng.normal(0.0, level.sigma_mm / 1000.0, 3)
    P = np.eye(4)
    P[:3, :3] = so3.exp(-d_theta) @ T[:3, :3]
    P[:3, 3] = T[:3, 3] - d_t
    return P


def build_for_object(config: Path, name: str, object_id: str, model_path: Path, region_class=None):
    """(estimator, None) or (None, why not): the config's entry `name`, its objects rebound; with `region_class`,
    every `region` entry built as that subclass (the `--colours-at-truth` oracle)."""
    from estimators.objects import ObjectRegistry, load_object
    from estimators.registry import EstimatorSpec, build_estimator
    from flextrack.assets import resolve

    doc = tomllib.loads(config.read_text())
    base_dir = config.resolve().parent
    objects = ObjectRegistry([load_object(object_id, model_path)])
    built, errors = {}, {}
    for entry in doc.get("estimators", []):
        entry_name = entry.get("name", entry["kind"])
        spec = EstimatorSpec(name=entry_name, kind=entry["kind"], objects=objects, object_ids=[object_id],
                             model=resolve(entry["model"], base_dir) if "model" in entry else None,
                             params=dict(entry.get("params", {})), base_dir=base_dir, built=dict(built))
        try:
            built[entry_name] = (region_class.from_spec(spec) if region_class is not None and spec.kind == "region"
                                 else build_estimator(spec))
        except Exception as exc:  # noqa: BLE001 - reported, not raised: the point is to say why
            errors[entry_name] = f"{type(exc).__name__}: {exc}"
        if entry_name == name:
            break
    if name in built:
        return built[name], None
    if name not in errors:
        return None, f"no estimator named '{name}' in {config}"
    entry = next(e for e in doc["estimators"] if e.get("name", e["kind"]) == name)
    parts = [f"its part '{v}' cannot: {errors[v]}" for v in entry.get("params", {}).values()
             if isinstance(v, str) and v in errors]
    return None, "; ".join(parts) if parts else errors[name]


@dataclass(frozen=True)
class Target:
    """What an object's answers are asked of and scored against."""

    object_id: str
    estimator: object
    points_O: np.ndarray  # (N, 3) m, the model's vertices (at most 4000, spread over it)
    diameter_m: float
    symmetries: np.ndarray  # (S, 4, 4), identity first: poses T_gt @ S look the same

    @property
    def center_O(self) -> np.ndarray:
        """The model's box centre (what a flipped prior turns about)."""
        return (self.points_O.min(axis=0) + self.points_O.max(axis=0)) / 2.0

    @classmethod
    def of(cls, estimator, obj) -> Target:
        v = obj.vertices
        pts = v if len(v) <= 4000 else v[np.linspace(0, len(v) - 1, 4000).astype(int)]
        return cls(obj.object_id, estimator, pts, obj.diameter_m, np.asarray(obj.symmetries, float))


def evaluate(targets: dict[int, Target], frames: list[Frame], levels: list[PriorLevel], draws: int, seed: int,
             width: int, height: int, fresh: bool = False, flip: bool = False, progress=None) -> dict:
    """Per level: {"summary", "by_object", "by_visib", "answers"} (see the module's docstring)."""
    from estimators.base import EstimateInput, EstimatorError, Status
    from flextrack.evaluation.colours_at_truth import ColoursAtTruth
    from flextrack.evaluation.nees_calibration import nees
    from flextrack.wire import pose_error

    images: dict[Path, np.ndarray] = {}
    add_s = {oid: metrics.AddS(t.points_O) for oid, t in targets.items() if len(t.symmetries) > 1}
    out = {}
    for level in levels:
        rows = []
        for d in range(draws):
            for fi, f in enumerate(frames):
                target = targets[f.obj_id]
                if f.rgb_path not in images:
                    images[f.rgb_path] = cv2.cvtColor(cv2.imread(str(f.rgb_path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
                camera = PinholeCamera.from_K(f.K, width, height)
                rng = np.random.default_rng([seed, *level.seed_key, d, f.scene, f.frame_id, f.instance])
                prior = None if level.sigma_mm is None else perturb(f.T_gt, level, rng)
                if prior is not None and flip:
                    prior = se3.turned_about_line_of_sight(prior, target.center_O)
                session = f"eval-{level.label}-{d}-{f.obj_id}" + (f"-{fi}" if fresh else "")
                inp = EstimateInput(frame_id=fi, capture_time_ns=0, object_id=target.object_id, session_id=session,
                                    camera=camera, image=images[f.rgb_path], prior_T_CO=prior,
                                    prior_covariance=None if prior is None else level.covariance)
                if isinstance(target.estimator, ColoursAtTruth):
                    target.estimator.truth_T_CO = f.T_gt
                start, cpu_start = time.perf_counter(), time.process_time()
                try:
                    ans = target.estimator.estimate(inp)
                    status, message = ans.status.value, ans.message
                except EstimatorError as exc:
                    ans, status, message = None, "REFUSED", str(exc)
                except Exception as exc:  # noqa: BLE001 - the service answers INTERNAL; counted, shown, not fatal
                    ans, status, message = None, "INTERNAL", f"{type(exc).__name__}: {exc}"
                ms = (time.perf_counter() - start) * 1e3
                cpu_ms = (time.process_time() - cpu_start) * 1e3  # this process's CPU: with one thread, one core's
                ok = ans is not None and ans.status == Status.OK and ans.T_CO is not None
                truths = [f.T_gt @ S for S in target.symmetries]
                proj = min(metrics.proj_px(ans.T_CO, T, camera, target.points_O) for T in truths) if ok else None
                add = (add_s[f.obj_id](ans.T_CO, f.T_gt) if f.obj_id in add_s
                       else metrics.add_m(ans.T_CO, f.T_gt, target.points_O)) if ok else None
                row = {"scene": f.scene, "frame": f.frame_id, "obj_id": f.obj_id, "instance": f.instance,
                       "visib": f.visib, "draw": d, "status": status, "ms": ms, "cpu_ms": cpu_ms,
                       "confidence": None if ans is None else float(ans.confidence),
                       "proj_px": proj, "add_m": add, "add_ok": bool(ok and add < 0.1 * target.diameter_m),
                       "prior_proj_px": None if prior is None else
                       min(metrics.proj_px(prior, T, camera, target.points_O) for T in truths),
                       "nees": min(nees(pose_error(ans.T_CO, T), ans.covariance) for T in truths)
                       if ok and ans.covariance is not None else None}
                if ok:  # where in the image the answer puts the object's centre, against the truth (a lean shows here)
                    answer, truth = (project_model(camera, T, target.center_O[None])[0] for T in (ans.T_CO, f.T_gt))
                    row["centre_offset_px"] = (answer - truth).tolist()
                else:
                    row["message"] = message
                rows.append(row)
                if progress:
                    progress(level, row)
        out[level.label] = {
            "summary": summarise(rows),
            "by_object": {str(o): summarise([r for r in rows if r["obj_id"] == o])
                          for o in sorted({r["obj_id"] for r in rows})},
            "by_visib": {band: summarise(group) for band in [visib_band(lo) for lo, _ in VISIB_BANDS] + ["unknown"]
                         if (group := [r for r in rows if visib_band(r["visib"]) == band])},
            "answers": rows}
    return out


def summarise(rows: list[dict]) -> dict:
    proj = np.array([r["proj_px"] if r["proj_px"] is not None else np.inf for r in rows])
    prior = [r["prior_proj_px"] for r in rows if r["prior_proj_px"] is not None]
    ms = np.array([r["ms"] for r in rows])
    cpu_ms = np.array([r["cpu_ms"] for r in rows])
    nees_values = [r["nees"] for r in rows if r["nees"] is not None]
    return {
        "answers": len(rows), "ok": int(np.isfinite(proj).sum()),
        "share_proj_5px": float(np.mean(proj < 5.0)), "share_add_10": float(np.mean([r["add_ok"] for r in rows])),
        "share_ok_wrong": float(np.mean(np.isfinite(proj) & (proj > WRONG_PX))),
        "median_proj_px": float(np.median(proj)) if np.isfinite(np.median(proj)) else None,  # None: most failed
        "prior_share_proj_5px": float(np.mean(np.array(prior) < 5.0)) if prior else None,
        "prior_median_proj_px": float(np.median(prior)) if prior else None,
        "ms_median": float(np.median(ms)), "ms_p90": float(np.percentile(ms, 90)),
        "cpu_ms_median": float(np.median(cpu_ms)), "cpu_ms_p90": float(np.percentile(cpu_ms, 90)),
        "nees_mean": float(np.mean(nees_values)) if nees_values else None,
        "nees_median": float(np.median(nees_values)) if nees_values else None,
        "nees_count": len(nees_values),
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bop", type=Path, required=True, help="BOP folder (models/, split/scene/...)")
    parser.add_argument("--obj-id", required=True,
                        help="BOP object id (the cat of LineMOD is 6), a comma list (1,5,6), or 'all' of models/")
    parser.add_argument("--estimator", default="region", help="an [[estimators]] name of --config")
    parser.add_argument("--config", type=Path, default=None,
                        help="service config declaring it (default: the service's default config)")
    parser.add_argument("--levels", default=DEFAULT_LEVELS, help="prior sigmas per axis, mm:deg, or none")
    parser.add_argument("--draws", type=int, default=5, help="priors per instance and level")
    parser.add_argument("--seed", type=int, default=0, help="seed of the priors drawn around the truth (default: %(default)s)")
    parser.add_argument("--split", default="test", help="the BOP split folder under --bop (default: %(default)s)")
    parser.add_argument("--part", choices=["all", "even", "odd"], default="all",
                        help="every frame, or every other frame of each scene (even: the first, third, ...; "
                             "odd: the others), to score on frames that did not tune (default: %(default)s)")
    parser.add_argument("--min-visib", type=float, default=0.0,
                        help="leave out instances less visible than this, a BOP visib_fract of 0-1 (default: %(default)s)")
    parser.add_argument("--limit", type=int, default=None, help="first N instances only")
    parser.add_argument("--fresh", action="store_true", help="every instance a new session (no colour history)")
    parser.add_argument("--flip", action="store_true",
                        help="turn every prior 180 deg about the camera's ray through the object (still claiming "
                             "the level's sigmas): a badly wrong prior the estimator should refuse")
    parser.add_argument("--colours-at-truth", action="store_true",
                        help="an oracle: every region fit learns its first colours at the true outline instead of "
                             "its start's (what region reaches when its colour model is right; never served)")
    parser.add_argument("--out", type=Path, default=None, help="result JSON (default: print only)")


def object_ids(text: str, models: Path) -> list[int]:
    """The BOP object ids an --obj-id names: 'all' of the models folder's obj_NNNNNN.ply, or a comma list."""
    if text.strip() == "all":
        return sorted(int(p.stem[4:]) for p in models.glob("obj_*.ply") if p.stem[4:].isdigit())
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise ValueError(f"--obj-id {text!r}: give BOP object ids (6, or 1,5,6) or 'all'") from None


def _fmt(x, pct=False):
    return "-" if x is None else (f"{100 * x:.1f} %" if pct else f"{x:.2f}")


def print_table(name: str, levels: dict) -> None:
    print(f"| {name} | prior | group | answers | < 5 px | ADD(-S) 10 % | OK > 20 px | median px | prior < 5 px "
          "| ms median (CPU) | NEES mean / median |")
    print("|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for label, level in levels.items():
        groups = [("all", level["summary"])] + [(f"obj {k}", v) for k, v in level["by_object"].items()] \
            + [(f"visib {k}", v) for k, v in level["by_visib"].items()]
        for group, s in groups:
            print(f"| {name} | {label} | {group} | {s['answers']} | {_fmt(s['share_proj_5px'], True)} | "
                  f"{_fmt(s['share_add_10'], True)} | {_fmt(s['share_ok_wrong'], True)} | {_fmt(s['median_proj_px'])} | "
                  f"{_fmt(s['prior_share_proj_5px'], True)} | {_fmt(s['ms_median'])} ({_fmt(s['cpu_ms_median'])}) | "
                  f"{_fmt(s['nees_mean'])} / {_fmt(s['nees_median'])} |")


def run(args: argparse.Namespace) -> int:
    from estimators.objects import load_object

    if args.config is None:
        from flextrack.assets import default_config_path
        args.config = default_config_path()
    prog = "flextrack evaluate prior"
    if not (args.bop / args.split).is_dir():
        print(f"{prog}: no BOP split folder {args.bop / args.split} (--bop DATASET --split {args.split})",
              file=sys.stderr)
        return 2
    try:
        obj_ids = object_ids(args.obj_id, args.bop / "models")
    except ValueError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
        return 2
    if not 0.0 <= args.min_visib <= 1.0 or args.draws < 1:
        print(f"{prog}: --min-visib is a fraction (0-1) and --draws at least 1", file=sys.stderr)
        return 2
    frames = bop_instances(args.bop, obj_ids, args.split, args.part, args.min_visib)[:args.limit]
    if not frames:
        print(f"{prog}: no instances of object(s) {args.obj_id} under {args.bop / args.split}", file=sys.stderr)
        return 2
    width, height = 640, 480
    cam_file = args.bop / "camera.json"
    if cam_file.is_file():
        cam = json.loads(cam_file.read_text())
        width, height = int(cam["width"]), int(cam["height"])
    levels = parse_levels(args.levels)
    present = sorted({f.obj_id for f in frames})
    result = {
        "command": command_line("evaluate", "prior"),
        **provenance(**{k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}),
        "seeds": {"seed": args.seed,
                  "rng": "numpy default_rng([seed, sigma in um, sigma in mdeg, draw, scene, frame, instance])"},
        "platform": platform.platform(),
        "frames": len({(f.scene, f.frame_id) for f in frames}), "instances": len(frames),
        "object_id": f"obj_{present[0]:06d}" if len(present) == 1 else [f"obj_{o:06d}" for o in present],
    }
    targets, errors = {}, []
    region_class = None
    if args.colours_at_truth:
        from flextrack.evaluation.colours_at_truth import ColoursAtTruth
        region_class = ColoursAtTruth
    for oid in present:
        object_id, model_path = f"obj_{oid:06d}", args.bop / "models" / f"obj_{oid:06d}.ply"
        estimator, error = build_for_object(args.config, args.estimator, object_id, model_path, region_class)
        if estimator is not None and region_class is not None and not isinstance(estimator, region_class):
            estimator, error = None, "--colours-at-truth is an oracle for a 'region' estimator; this one is not"
        if estimator is None:
            errors.append(error)
            print(f"{args.estimator} cannot run on {object_id}: {error}")
            continue
        targets[oid] = Target.of(estimator, load_object(object_id, model_path))
    if errors:
        result["error"] = "; ".join(errors)
    else:
        def progress(level, row, _count=[0]):  # noqa: B006 - a counter across calls
            _count[0] += 1
            if _count[0] % 200 == 0:
                print(f"  {_count[0]} answers ({level.label})", file=sys.stderr, flush=True)
        result["levels"] = evaluate(targets, frames, levels, args.draws, args.seed, width, height,
                                    fresh=args.fresh, flip=args.flip, progress=progress)
        print_table(args.estimator, result["levels"])
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.out}")
    return 1 if errors else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="flextrack evaluate prior", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
