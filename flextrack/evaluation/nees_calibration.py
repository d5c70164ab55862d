"""`flextrack evaluate nees`: are the estimators' pose covariances calibrated?

For each answer with a pose, the NEES (normalised estimation error squared) is e^T Sigma^-1 e, with
e the true error of the pose in the wire convention (flextrack.wire.pose_error: rotation first, both
in the camera frame) and Sigma the covariance the estimator sent. For a calibrated, Gaussian
estimator it is chi-square with 6 degrees of freedom, and the mean of N answers is
Gamma(shape 3N, scale 2/N): its 95 % interval is the criterion (about [5.53, 6.49] for N = 200).
The median (5.35 for chi2(6)) and the share above chi2(6)'s 95 % quantile (12.59; 5 % expected)
show whether a mean is made by a few outliers.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from flextrack.provenance import provenance

CHI2_6_Q95 = 12.592  # scipy.stats.chi2.ppf(0.95, 6)


def nees(e: np.ndarray, covariance: np.ndarray) -> float:
    """e^T Sigma^-1 e of one answer (6-vectors in the wire convention)."""
    e = np.asarray(e, dtype=float)
    return float(e @ np.linalg.solve(covariance, e))


def mean_interval(n: int, level: float = 0.95) -> tuple[float, float]:
    """The `level` interval of the mean of n iid chi2(6) values: Gamma(shape 3n, scale 2/n)."""
    from scipy.stats import gamma

    lo, hi = gamma.ppf([(1 - level) / 2, (1 + level) / 2], a=3 * n, scale=2.0 / n)
    return float(lo), float(hi)


def summarise(values) -> dict:
    """N, mean, its 95 % interval, pass, median and share above 12.59 of a set of NEES values."""
    v = np.asarray(list(values), dtype=float)
    if not len(v):
        return {"n": 0, "mean": None, "interval": None, "median": None, "share_above_q95": None, "passed": False}
    lo, hi = mean_interval(len(v))
    mean = float(np.mean(v))
    return {"n": len(v), "mean": mean, "interval": [lo, hi], "median": float(np.median(v)),
            "share_above_q95": float(np.mean(v > CHI2_6_Q95)), "passed": bool(lo <= mean <= hi)}


def answer_row(frame: int, T_est: np.ndarray, T_true: np.ndarray, covariance: np.ndarray, camera, vertices) -> dict:
    """One answer scored: its NEES, mean 2D error (px) and error e (wire convention; deg, deg, deg, mm, mm, mm)."""
    from flextrack import wire
    from flextrack.geometry import metrics

    e = wire.pose_error(T_est, T_true)
    return {"frame": frame, "nees": nees(e, covariance), "proj_px": metrics.proj_px(T_est, T_true, camera, vertices),
            "error": [*np.degrees(e[:3]).tolist(), *(1e3 * e[3:]).tolist()]}


def inflation_factor(values) -> float:
    """The one factor k by which covariances are scaled (Sigma -> k Sigma) to bring the mean NEES of
    these answers to 6, its expectation."""
    return float(np.mean(np.asarray(list(values), dtype=float)) / 6.0)


# ---- answers: (NEES, 2D error) per answer with a pose -------------------------------------------

def _default_object():
    from estimators.objects import load_object
    from flextrack import assets

    return load_object("default", assets.default_object_model())


def pnp_answers(n: int, seed: int, noise_px: float = 1.0, outlier_share: float = 0.3, estimator=None,
                obj=None) -> list[dict]:
    """n PnP solves of the default object's registered keypoints projected at random poses (0.45-1.5 m,
    anywhere in a 640x480 view, seen from above), each coordinate with N(0, noise_px^2) noise; in a
    share `outlier_share` of the frames one keypoint is moved 15-60 px (RANSAC's to reject)."""
    from estimators.base import EstimateInput, Status
    from estimators.objects import ObjectRegistry
    from estimators.pnp import PnpEstimator
    from flextrack.geometry import se3
    from flextrack.geometry.camera import PinholeCamera
    from flextrack.training.pvnet_data import random_pose

    obj = obj or _default_object()
    estimator = estimator or PnpEstimator(ObjectRegistry([obj]))
    camera = PinholeCamera.linemod()
    centre = (obj.vertices.min(axis=0) + obj.vertices.max(axis=0)) / 2
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        T = random_pose(rng, camera, centre, (0.45, 1.5))
        uv = camera.project(se3.transform_points(T, obj.keypoints))
        noisy = uv + rng.normal(0.0, noise_px, uv.shape)
        if rng.uniform() < outlier_share:
            k = rng.integers(len(uv))
            angle = rng.uniform(0, 2 * np.pi)
            noisy[k] += rng.uniform(15, 60) * np.array([np.cos(angle), np.sin(angle)])
        kp = np.column_stack([np.arange(len(uv)), noisy])
        out = estimator.estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=camera, keypoints=kp))
        if out.status is not Status.OK:
            continue
        rows.append(answer_row(i, out.T_CO, T, out.covariance, camera, obj.vertices))
    return rows


def gt_oracle_answers(sequence_root: Path, noise_t_m: float, noise_r_deg: float, seed: int,
                      limit: int | None = None) -> list[dict]:
    """The noisy oracle's answers at the frames of a sequence folder (at most `limit`, evenly spread),
    scored against the folder's ground truth."""
    from estimators.base import EstimateInput, Status
    from estimators.gt_oracle import GtOracleEstimator
    from estimators.objects import load_object
    from flextrack.formats import sequence as sequence_io

    seq = sequence_io.load(sequence_root)
    oracle = GtOracleEstimator(sequence_roots=[sequence_root], noise_t_m=noise_t_m, noise_r_deg=noise_r_deg,
                               seed=seed)
    vertices = load_object(seq.object_id, seq.model_path).vertices
    ids = [int(f) for f in seq.frame_ids if int(f) in seq.gt_T_CO]
    times = dict(zip((int(f) for f in seq.frame_ids), (int(t) for t in seq.frame_times_ns)))
    if limit is not None and len(ids) > limit:
        ids = [ids[int(i)] for i in np.linspace(0, len(ids) - 1, limit).round()]
    rows = []
    for frame_id in ids:
        out = oracle.estimate(EstimateInput(frame_id=frame_id, capture_time_ns=times[frame_id]))
        if out.status is not Status.OK:
            continue
        rows.append(answer_row(frame_id, out.T_CO, seq.gt_T_CO[frame_id], out.covariance, seq.camera, vertices))
    return rows



def pvnet_answers(n: int, seed: int, jpeg: int | None, estimators: dict, obj, object_path: Path,
                  progress=None) -> dict[str, list[dict]]:
    """Each pvnet estimator of `estimators` (name -> estimator) on the same n rendered frames of
    `flextrack train pvnet-eval` (the simulator's rooms, seed `seed`), sent through JPEG at quality
    `jpeg` as the device sends them (None: as rendered); `obj` the ObjectModel of `object_path`."""
    from estimators.base import EstimateInput, Status
    from flextrack.geometry import metrics
    from flextrack.training import evaluate

    frames = evaluate.rendered_frames(object_path, n, seed, scenes=4)
    if jpeg is not None:
        frames = evaluate.as_sent(frames, jpeg, "444")
    rows: dict[str, list[dict]] = {name: [] for name in estimators}
    for i, (_, rgb, camera, T, _) in enumerate(frames):
        for name, estimator in estimators.items():
            out = estimator.estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=camera, image=rgb))
            if out.status is not Status.OK:
                continue
            rows[name].append({**answer_row(i, out.T_CO, T, out.covariance, camera, obj.vertices),
                               "add_ok": bool(metrics.add_m(out.T_CO, T, obj.vertices) < 0.1 * obj.diameter_m)})
        if progress is not None:
            progress(i + 1)
    return rows


# ---- the command ------------------------------------------------------------------------------

ESTIMATORS = ("gt_oracle", "pnp", "pvnet")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out/nees"),
                        help="folder for nees.json (summaries, provenance) and answers.csv (every held-out answer)")
    parser.add_argument("--estimators", nargs="+", choices=ESTIMATORS, default=list(ESTIMATORS),
                        help="which estimators to evaluate")
    parser.add_argument("--max-2d-px", type=float, default=20.0,
                        help="the criterion's answers: those with a mean 2D error below this (gross outliers out)")
    parser.add_argument("--tune-seed", type=int, default=1, help="gt_oracle and pnp: the tuning set's seed")
    parser.add_argument("--seed", type=int, default=2, help="gt_oracle and pnp: the held-out set's seed")
    g = parser.add_argument_group("gt_oracle (the paper's Noisy backend on a simulated sequence)")
    g.add_argument("--oracle-motion", default="circular", choices=("translational", "circular"),
                   help="the simulated sequence's motion program (default: %(default)s)")
    g.add_argument("--oracle-level", default="medium", choices=("easy", "medium", "hard"),
                   help="its speed level (default: %(default)s)")
    g.add_argument("--oracle-answers", type=int, default=1000, help="frames asked, evenly over the sequence")
    g.add_argument("--noise-t-m", type=float, default=0.003, help="translation noise per axis, m (default: %(default)g)")
    g.add_argument("--noise-r-deg", type=float, default=0.3, help="rotation noise per axis, deg (default: %(default)g)")
    g = parser.add_argument_group("pnp (the default object's keypoints projected at random poses, noisy)")
    g.add_argument("--pnp-answers", type=int, default=1000, help="held-out solves")
    g.add_argument("--pnp-tune-answers", type=int, default=4000, help="tuning solves")
    g.add_argument("--pnp-noise-px", type=float, nargs="+", default=[1.0],
                   help="keypoint noise per coordinate, px; several values: one pnp entry each, named by its noise")
    g.add_argument("--pnp-outliers", type=float, default=0.3, help="share of frames with one keypoint 15-60 px off")
    g = parser.add_argument_group("pvnet (rendered frames of the default object, `flextrack train pvnet-eval`'s)")
    g.add_argument("--pvnet-frames", type=int, default=200, help="frames per set")
    g.add_argument("--pvnet-tune-seeds", type=int, nargs="+", default=[777, 778],
                   help="tuning frames, --pvnet-frames per seed (777: pvnet-eval's tuning seed)")
    g.add_argument("--pvnet-seed", type=int, default=20261122, help="held-out frames (pvnet-eval's default)")
    g.add_argument("--jpeg", type=int, default=90, help="JPEG quality the frames are sent at (0: as rendered)")
    g.add_argument("--model", type=Path, help="PVNet ONNX (default: the shipped model)")
    parser.description = (parser.description or "") + (
        ". Exit status: 0 when every estimator's held-out mean NEES (answers under --max-2d-px) is inside its 95 % "
        "interval; 1 when one is not (each named on stderr: a covariance that claims too much or too little); 2 for "
        "a bad argument.")


def argument_problem(args) -> str | None:
    """One line for an argument that cannot work, before any work is done."""
    from flextrack.runners.cli_checks import numbers_problem, out_folder_problem

    many = 10_000_000
    return numbers_problem([
        ("--oracle-answers", args.oracle_answers, 1, many, True), ("--pnp-answers", args.pnp_answers, 1, many, True),
        ("--pnp-tune-answers", args.pnp_tune_answers, 1, many, True),
        ("--pvnet-frames", args.pvnet_frames, 1, many, True), ("--max-2d-px", args.max_2d_px, 0, 1e6),
        ("--noise-t-m", args.noise_t_m, 0, 10, True), ("--noise-r-deg", args.noise_r_deg, 0, 180, True),
        *(("--pnp-noise-px", x, 0, 1000, True) for x in args.pnp_noise_px),
        ("--pnp-outliers", args.pnp_outliers, 0, 1, True),
        ("--jpeg", args.jpeg, 0, 100, True)]) or out_folder_problem(args.out)


def _entry(name: str, tune: list[dict], held: list[dict], stored: float, max_px: float, **extra) -> dict:
    """Held-out summaries (all answers and those under max_px, with their mean error: a bias no
    covariance of zero mean describes) and the factor the tuning set asks for: the raw formula's mean
    NEES / 6 there (the NEES with the stored factor times that factor)."""
    good_tune = [r for r in tune if r["proj_px"] < max_px]
    good_held = [r for r in held if r["proj_px"] < max_px]
    fitted = inflation_factor([r["nees"] * stored for r in good_tune]) if tune else None
    mean_error = np.mean([r["error"] for r in good_held], axis=0).tolist() if good_held else None
    return {"estimator": name, "stored_inflation": stored, "fitted_inflation": fitted,
            "tuning_answers": len(good_tune), "heldout_all": summarise(r["nees"] for r in held),
            "heldout_below_max_2d": {**summarise(r["nees"] for r in good_held), "mean_error_deg_mm": mean_error},
            **extra, "answers": held}


ANSWER_COLUMNS = ("estimator", "frame", "nees", "proj_px", "rx_deg", "ry_deg", "rz_deg", "tx_mm", "ty_mm", "tz_mm")


def write_results(result: dict, out: Path) -> Path:
    """`nees.json` (the summaries and the provenance) and `answers.csv` (every held-out answer: its NEES,
    2D error and error e in the camera frame) into `out`; returns the JSON's path."""
    import csv
    import json

    out.mkdir(parents=True, exist_ok=True)
    with open(out / "answers.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(ANSWER_COLUMNS)
        for e in result["estimators"]:
            for r in e["answers"]:
                writer.writerow([e["estimator"], r["frame"], f"{r['nees']:.6g}", f"{r['proj_px']:.6g}",
                                 *(f"{v:.6g}" for v in r["error"])])
    summaries = {**result, "estimators": [{k: v for k, v in e.items() if k != "answers"} for e in result["estimators"]]}
    path = out / "nees.json"
    path.write_text(json.dumps(summaries, indent=1))
    return path


def run(args) -> int:
    import sys
    import time

    problem = argument_problem(args)
    if problem:
        print(f"flextrack evaluate nees: {problem}", file=sys.stderr)
        return 2
    started = time.perf_counter()
    options = {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items() if not k.startswith("_")}
    result = {"provenance": provenance(command="flextrack evaluate nees", **options), "estimators": []}
    entries = result["estimators"]
    try:
        if "gt_oracle" in args.estimators:
            entries.append(_gt_oracle(args))
        if "pnp" in args.estimators:
            entries.extend(_pnp(args, noise, name="pnp" if len(args.pnp_noise_px) == 1 else f"pnp {noise:g} px")
                           for noise in args.pnp_noise_px)
        if "pvnet" in args.estimators:
            entries.extend(_pvnet(args))
    except (FileNotFoundError, ValueError) as exc:
        print(f"flextrack evaluate nees: {exc}", file=sys.stderr)
        return 2
    prov = result["provenance"]
    prov["wall_s"] = round(time.perf_counter() - started, 1)
    path = write_results(result, args.out)
    print(table(entries, args.max_2d_px))
    print(f"wrote {path} and answers.csv ({prov['wall_s']:.0f} s; commit {prov['commit'] or '?'}"
          f"{' dirty' if prov['dirty'] else ''})")
    failed = [e for e in entries if not e["heldout_below_max_2d"]["passed"]]
    if failed:
        print("flextrack evaluate nees: not calibrated: " + "; ".join(miscalibration(e) for e in failed),
              file=sys.stderr)
        return 1
    return 0


def miscalibration(entry: dict) -> str:
    """Why an estimator failed, in a clause: its held-out mean NEES against the interval, and which way."""
    s = entry["heldout_below_max_2d"]
    if not s["n"]:
        return f"{entry['estimator']} has no held-out answer under --max-2d-px"
    lo, hi = s["interval"]
    way = "errors larger than its covariance says" if s["mean"] > hi else "covariance larger than its errors"
    return f"{entry['estimator']} mean NEES {s['mean']:.2f} outside [{lo:.2f}, {hi:.2f}] ({way})"


def _gt_oracle(args) -> dict:
    """Tuning and held-out: a sequence and a noise seed each (--tune-seed, --seed)."""
    from flextrack.simulator.generate import generate_sequence

    sets = {}
    for role, seed in (("tune", args.tune_seed), ("held", args.seed)):
        root = args.out / "sequences" / f"{args.oracle_motion}_{args.oracle_level}_seed{seed}"
        if not (root / "rig.yaml").is_file():
            generate_sequence(args.oracle_motion, args.oracle_level, root, fps=60.0, seed=seed)
        sets[role] = gt_oracle_answers(root, args.noise_t_m, args.noise_r_deg, seed, args.oracle_answers)
    return _entry("gt_oracle", sets["tune"], sets["held"], 1.0, args.max_2d_px,
                  settings={"noise_t_m": args.noise_t_m, "noise_r_deg": args.noise_r_deg, "fps": 60,
                            "sequence": f"{args.oracle_motion} {args.oracle_level}"})


def _pnp(args, noise_px: float, name: str = "pnp") -> dict:
    from estimators.objects import ObjectRegistry
    from estimators.pnp import PnpEstimator

    obj = _default_object()
    estimator = PnpEstimator(ObjectRegistry([obj]))
    kw = {"noise_px": noise_px, "outlier_share": args.pnp_outliers, "estimator": estimator, "obj": obj}
    return _entry(name, pnp_answers(args.pnp_tune_answers, args.tune_seed, **kw),
                  pnp_answers(args.pnp_answers, args.seed, **kw), estimator.inflation, args.max_2d_px,
                  settings={"noise_px": noise_px, "outlier_share": args.pnp_outliers, "keypoints": len(obj.keypoints),
                            "ransac_px": estimator.ransac_px})


def _pvnet(args) -> list[dict]:
    """The default estimator (pose refined on the outline: the refinement's covariance) and the same
    with refine = false (PnP's pose: the voted keypoints' covariance), on the same frames."""
    import sys

    from estimators.objects import ObjectRegistry, load_object
    from estimators.pvnet import PvnetEstimator
    from flextrack import assets

    object_path = assets.default_object_model()
    obj = load_object("default", object_path)
    model = args.model or assets.pvnet_model_path()
    estimators = {"pvnet": PvnetEstimator(ObjectRegistry([obj]), model),
                  "pvnet refine=false": PvnetEstimator(ObjectRegistry([obj]), model, refine=False)}
    jpeg = args.jpeg or None
    sets = {"tune": {name: [] for name in estimators}}
    for role, seed in [("tune", s) for s in args.pvnet_tune_seeds] + [("held", args.pvnet_seed)]:
        def progress(i, seed=seed):
            if i % 50 == 0:
                print(f"pvnet frames of seed {seed}: {i}/{args.pvnet_frames}", file=sys.stderr, flush=True)
        rows = pvnet_answers(args.pvnet_frames, seed, jpeg, estimators, obj, object_path, progress)
        if role == "held":
            sets["held"] = rows
        else:
            for name in estimators:
                sets["tune"][name] += rows[name]
    settings = {"frames": args.pvnet_frames, "jpeg": jpeg, "model": str(model)}
    return [_entry("pvnet", sets["tune"]["pvnet"], sets["held"]["pvnet"], estimators["pvnet"].refine_inflation,
                   args.max_2d_px, settings=settings, covariance="refinement"),
            _entry("pvnet refine=false", sets["tune"]["pvnet refine=false"], sets["held"]["pvnet refine=false"],
                   estimators["pvnet refine=false"].keypoint_inflation, args.max_2d_px, settings=settings,
                   covariance="voted keypoints")]


def table(entries: list[dict], max_px: float) -> str:
    """The held-out figures as a Markdown table; the mean error (a bias) on the criterion's answers."""
    lines = [("| estimator | answers | N | mean NEES | 95 % interval | median | share > 12.59 | pass | inflation (fitted) "
              "| mean error: rotation deg (x, y, z); translation mm (x, y, z) |"),
             "|---|---|---:|---:|---|---:|---:|---|---|---|"]
    for e in entries:
        for label, key in (("all", "heldout_all"), (f"2D < {max_px:g} px", "heldout_below_max_2d")):
            s = e[key]
            if not s["n"]:
                lines.append(f"| {e['estimator']} | {label} | 0 | - | - | - | - | - | | |")
                continue
            fitted = "-" if e["fitted_inflation"] is None else f"{e['fitted_inflation']:.3g}"
            bias = s.get("mean_error_deg_mm")
            bias = "" if bias is None else (", ".join(f"{v:+.2f}" for v in bias[:3]) + "; "
                                            + ", ".join(f"{v:+.1f}" for v in bias[3:]))
            lines.append(f"| {e['estimator']} | {label} | {s['n']} | {s['mean']:.2f} | [{s['interval'][0]:.2f}, "
                         f"{s['interval'][1]:.2f}] | {s['median']:.2f} | {100 * s['share_above_q95']:.1f} % | "
                         f"{'yes' if s['passed'] else 'NO'} | {e['stored_inflation']:g} ({fitted}) | {bias} |")
    return "\n".join(lines)
