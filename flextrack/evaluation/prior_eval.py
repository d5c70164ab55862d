"""`flextrack evaluate prior`: score an estimator on a BOP folder with priors drawn around the
ground truth.

For every frame of the folder showing the object, and every prior level (per-axis sigmas in mm and
degrees, or `none`), `draws` priors are drawn (seeded): e = (d_theta, d_t) ~ N(0, diag(sigma_r^2,
sigma_t^2)) in the wire convention (flextrack.wire: R_true = Exp(d_theta) R_prior, t_true =
t_prior + d_t), sent with that diagonal covariance. Reported per level: the share of answers under
5 px of 2D projection error (BOP's proj over the model's vertices), the share under ADD 10 % of the
object's diameter, the median 2D error (a failure counts as infinitely far), the same for the
priors themselves (what the estimator started from), the time per estimate and the mean NEES of the
answers' covariances. Draw d of every level runs as its own session through the frames in order
(the colour histograms carry over, as on a device), unless `--fresh` starts each frame afresh.

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
from flextrack.geometry import metrics, so3
from flextrack.geometry.camera import PinholeCamera
from flextrack.provenance import provenance

DEFAULT_LEVELS = "10:5,20:10,none"


@dataclass(frozen=True)
class Frame:
    scene: int
    frame_id: int
    rgb_path: Path
    K: np.ndarray
    T_gt: np.ndarray


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
    frames = []
    for scene_dir in sorted(p for p in (folder / split).iterdir() if p.is_dir()):
        gt = bop.read_scene_gt(scene_dir / "scene_gt.json", obj_id)
        Ks = bop.read_scene_camera(scene_dir / "scene_camera.json")
        for frame_id in sorted(gt):
            rgb = next((scene_dir / "rgb" / f"{frame_id:06d}{ext}" for ext in (".png", ".jpg")
                        if (scene_dir / "rgb" / f"{frame_id:06d}{ext}").is_file()), None)
            if rgb is not None:
                frames.append(Frame(int(scene_dir.name), frame_id, rgb, Ks[frame_id], gt[frame_id]))
    return frames[:limit] if limit else frames


def perturb(T: np.ndarray, level: PriorLevel, rng: np.random.Generator) -> np.ndarray:
    """A prior T_prior with T = (Exp(d_theta) R_prior, t_prior + d_t), e drawn at the level's sigmas."""
    d_theta = rng.normal(0.0, np.radians(level.sigma_deg), 3)
    d_t = rng.normal(0.0, level.sigma_mm / 1000.0, 3)
    P = np.eye(4)
    P[:3, :3] = so3.exp(-d_theta) @ T[:3, :3]
    P[:3, 3] = T[:3, 3] - d_t
    return P


def build_for_object(config: Path, name: str, object_id: str, model_path: Path):
    """(estimator, None) or (None, why not): the config's entry `name`, its objects rebound."""
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
            built[entry_name] = build_estimator(spec)
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


def evaluate(estimator, frames: list[Frame], levels: list[PriorLevel], draws: int, seed: int,
             object_id: str, vertices: np.ndarray, diameter_m: float, width: int, height: int,
             fresh: bool = False, progress=None) -> dict:
    from estimators.base import EstimateInput, EstimatorError, Status
    from flextrack.evaluation.nees_calibration import nees
    from flextrack.wire import pose_error

    images = {f.rgb_path: cv2.cvtColor(cv2.imread(str(f.rgb_path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
              for f in frames}
    pts = vertices if len(vertices) <= 4000 else vertices[np.linspace(0, len(vertices) - 1, 4000).astype(int)]
    out = {}
    for level in levels:
        rows = []
        for d in range(draws):
            rng = np.random.default_rng([seed, *level.seed_key, d])
            for fi, f in enumerate(frames):
                camera = PinholeCamera.from_K(f.K, width, height)
                prior = None if level.sigma_mm is None else perturb(f.T_gt, level, rng)
                session = f"eval-{level.label}-{d}" + (f"-{fi}" if fresh else "")
                inp = EstimateInput(frame_id=fi, capture_time_ns=0, object_id=object_id, session_id=session,
                                    camera=camera, image=images[f.rgb_path], prior_T_CO=prior,
                                    prior_covariance=None if prior is None else level.covariance)
                start, cpu_start = time.perf_counter(), time.process_time()
                try:
                    ans = estimator.estimate(inp)
                    status, message = ans.status.value, ans.message
                except EstimatorError as exc:
                    ans, status, message = None, "REFUSED", str(exc)
                except Exception as exc:  # noqa: BLE001 - the service answers INTERNAL; counted, shown, not fatal
                    ans, status, message = None, "INTERNAL", f"{type(exc).__name__}: {exc}"
                ms = (time.perf_counter() - start) * 1e3
                cpu_ms = (time.process_time() - cpu_start) * 1e3  # this process's CPU: with one thread, one core's
                ok = ans is not None and ans.status == Status.OK and ans.T_CO is not None
                row = {"scene": f.scene, "frame": f.frame_id, "draw": d, "status": status, "ms": ms, "cpu_ms": cpu_ms,
                       "confidence": None if ans is None else float(ans.confidence),
                       "proj_px": metrics.proj_px(ans.T_CO, f.T_gt, camera, pts) if ok else None,
                       "add_m": metrics.add_m(ans.T_CO, f.T_gt, pts) if ok else None,
                       "prior_proj_px": metrics.proj_px(prior, f.T_gt, camera, pts) if prior is not None else None,
                       "nees": nees(pose_error(ans.T_CO, f.T_gt), ans.covariance)
                       if ok and ans.covariance is not None else None}
                if not ok:
                    row["message"] = message
                rows.append(row)
                if progress:
                    progress(level, row)
        out[level.label] = {"summary": summarise(rows, diameter_m), "answers": rows}
    return out


def summarise(rows: list[dict], diameter_m: float) -> dict:
    proj = np.array([r["proj_px"] if r["proj_px"] is not None else np.inf for r in rows])
    add = np.array([r["add_m"] if r["add_m"] is not None else np.inf for r in rows])
    prior = [r["prior_proj_px"] for r in rows if r["prior_proj_px"] is not None]
    ms = np.array([r["ms"] for r in rows])
    cpu_ms = np.array([r["cpu_ms"] for r in rows])
    nees_values = [r["nees"] for r in rows if r["nees"] is not None]
    return {
        "answers": len(rows), "ok": int(np.isfinite(proj).sum()),
        "share_proj_5px": float(np.mean(proj < 5.0)), "share_add_10": float(np.mean(add < 0.1 * diameter_m)),
        "median_proj_px": float(np.median(proj)) if np.isfinite(np.median(proj)) else None,  # None: most failed
        "prior_share_proj_5px": float(np.mean(np.array(prior) < 5.0)) if prior else None,
        "prior_median_proj_px": float(np.median(prior)) if prior else None,
        "ms_median": float(np.median(ms)), "ms_p90": float(np.percentile(ms, 90)),
        "cpu_ms_median": float(np.median(cpu_ms)), "cpu_ms_p90": float(np.percentile(cpu_ms, 90)),
        "nees_mean": float(np.mean(nees_values)) if nees_values else None,
        "nees_median": float(np.median(nees_values)) if nees_values else None,
    }


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--bop", type=Path, required=True, help="BOP folder (models/, split/scene/...)")
    parser.add_argument("--obj-id", type=int, required=True, help="BOP object id (the cat of LineMOD is 6)")
    parser.add_argument("--estimator", default="region", help="an [[estimators]] name of --config")
    parser.add_argument("--config", type=Path, default=None,
                        help="service config declaring it (default: the service's default config)")
    parser.add_argument("--levels", default=DEFAULT_LEVELS, help="prior sigmas per axis, mm:deg, or none")
    parser.add_argument("--draws", type=int, default=5, help="priors per frame and level")
    parser.add_argument("--seed", type=int, default=0, help="seed of the priors drawn around the truth (default: %(default)s)")
    parser.add_argument("--split", default="test", help="the BOP split folder under --bop (default: %(default)s)")
    parser.add_argument("--limit", type=int, default=None, help="first N frames only")
    parser.add_argument("--fresh", action="store_true", help="every frame a new session (no colour history)")
    parser.add_argument("--out", type=Path, default=None, help="result JSON (default: print only)")


def run(args: argparse.Namespace) -> int:
    from estimators.objects import load_object

    if args.config is None:
        from flextrack.assets import default_config_path
        args.config = default_config_path()
    model_path = args.bop / "models" / f"obj_{args.obj_id:06d}.ply"
    object_id = f"obj_{args.obj_id:06d}"
    if not (args.bop / args.split).is_dir():
        print(f"flextrack evaluate prior: no BOP split folder {args.bop / args.split} (--bop DATASET --split "
              f"{args.split})", file=sys.stderr)
        return 2
    frames = bop_frames(args.bop, args.obj_id, args.split, args.limit)
    if not frames:
        print(f"flextrack evaluate prior: no frames of object {args.obj_id} under {args.bop / args.split}",
              file=sys.stderr)
        return 2
    width, height = 640, 480
    cam_file = args.bop / "camera.json"
    if cam_file.is_file():
        cam = json.loads(cam_file.read_text())
        width, height = int(cam["width"]), int(cam["height"])
    levels = parse_levels(args.levels)
    result = {
        "command": "flextrack evaluate prior " + " ".join(sys.argv[3:] if sys.argv[1:3] == ["evaluate", "prior"]
                                                          else sys.argv[1:]),
        **provenance(**{k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()}),
        "seeds": {"seed": args.seed, "rng": "numpy default_rng([seed, sigma in um, sigma in mdeg, draw])"},
        "platform": platform.platform(),
        "frames": len(frames), "object_id": object_id,
    }
    estimator, error = build_for_object(args.config, args.estimator, object_id, model_path)
    if estimator is None:
        result["error"] = error
        print(f"{args.estimator} cannot run on {object_id}: {error}")
    else:
        obj = load_object(object_id, model_path)
        result["levels"] = evaluate(estimator, frames, levels, args.draws, args.seed, object_id, obj.vertices,
                                    obj.diameter_m, width, height, fresh=args.fresh)
        print(f"| {args.estimator} | prior | answers | < 5 px | ADD 10 % | median px | prior < 5 px | prior median px "
              "| ms median (CPU) | NEES mean / median |")
        print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
        for label, level in result["levels"].items():
            s = level["summary"]

            def fmt(x, pct=False):
                return "-" if x is None else (f"{100 * x:.1f} %" if pct else f"{x:.2f}")
            print(f"| {args.estimator} | {label} | {s['answers']} | {fmt(s['share_proj_5px'], True)} | "
                  f"{fmt(s['share_add_10'], True)} | {fmt(s['median_proj_px'])} | "
                  f"{fmt(s['prior_share_proj_5px'], True)} | {fmt(s['prior_median_proj_px'])} | "
                  f"{fmt(s['ms_median'])} ({fmt(s['cpu_ms_median'])}) | {fmt(s['nees_mean'])} / {fmt(s['nees_median'])} |")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.out}")
    return 0 if estimator is not None else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="flextrack evaluate prior", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
