"""`flextrack experiment table2|ablation|timing|euroc|filter|bound --out DIR`: the paper's experiments,
rerun, and the error-state filter's own checks and bound.

Each writes a Markdown report, CSV tables, PNG plots and TUM trajectories under DIR, and `NAME.json`
with the run's provenance (flextrack.provenance: options, seeds, commit, dirty, host, date).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from client_sdk.options import PRESETS
from flextrack.experiments import paper
from flextrack.provenance import of_args
from flextrack.runners.cli_checks import deprecated_alias
from flextrack.simulator.euroc_cli import xyz

EXPERIMENTS = ("table2", "ablation", "timing", "euroc", "filter", "bound")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("experiment", choices=EXPERIMENTS,
                        help="which one; each writes NAME.md (its report), CSV tables, PNG plots, TUM trajectories "
                        "and NAME.json (options, seeds, commit, date) under --out")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--seeds", type=int, default=1, help="table2, filter, bound: number of seeds (--seed .. --seed + N - 1)")
    parser.add_argument("--seed", type=int, default=0,
                        help="ablation, timing, euroc: the seed; table2, filter, bound: the first of --seeds")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds of motion per simulated sequence")
    parser.add_argument("--fps", type=float, nargs="+",
                        help=f"table2, bound: frame rates among {list(paper.FPS)} (all four unless given; 30 and 120 with "
                        f"--backend); euroc: the one frame rate (default: {paper.EUROC_FPS:g}, the paper's real-data rate)")
    parser.add_argument("--in-process", action="store_true",
                        help="call the backend in-process instead of gRPC (timing always does)")
    parser.add_argument("--jobs", type=int, default=None, metavar="N",
                        help="table2 (oracles), bound: cells run at once, each process with its own backend server "
                        "(default: one per CPU; the figures do not depend on it)")
    parser.add_argument("--backend", default="oracles",
                        help="table2: 'oracles' (GT and Noisy, the paper's table) or an image estimator of --config "
                        "(e.g. pvnet), run beside gt_oracle on rendered frames (its cells unless given: translational "
                        "and circular medium at 30 and 120 FPS)")
    parser.add_argument("--config", type=Path, help="table2 --backend: the service config (default "
                        "service/default_config.toml)")
    parser.add_argument("--backend-ms", type=float, default=145.0,
                        help="table2 --backend: modelled compute time of the estimator per frame, ms (virtual time; "
                        "145 = pvnet's whole-frame cost when the stored pvnet tables were made, kept so they can be rerun "
                        "alike; `flextrack bench pvnet` measures what it costs now, docs/benchmarks.md)")
    parser.add_argument("--data", type=Path, help="euroc: the EuRoC folder (default ../shared/data/euroc_v1_02_medium); "
                        "ablation: run on this recording (a hand-held one, EuRoC layout) instead of the simulated programs")
    parser.add_argument("--tracker", choices=PRESETS, default=None,
                        help="euroc: also run this tracker, as `flextrack track --tracker` (default: only the "
                        "experiment's own variants full, bscm_off, filter)")
    parser.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                        help="euroc: also run the tracker with this option changed, as `flextrack track --set` "
                        "(on --tracker, default filter; repeatable)")
    deprecated_alias(parser, "--preset", "--tracker", choices=PRESETS)
    parser.add_argument("--object-distance", type=float, metavar="M",
                        help="euroc: place the object where the camera looks most at this distance (default: "
                        "convert-euroc's choice)")
    parser.add_argument("--object-position", type=xyz, metavar="X,Y,Z",
                        help="euroc: put the object's centre here, world frame, m (default: placed automatically)")


def custom_tracker(args):
    """(label, TrackerOptions) of --tracker/--set, or None when neither is given."""
    if args.tracker is None and not args.set:
        return None
    from flextrack.runners.track_cli import tracker_options

    flags = argparse.Namespace(tracker=args.tracker or "filter", set=args.set, no_bscm=False, no_pia=False,
                               imu_only=False, integrator=None)
    return " ".join([f"preset {flags.tracker}", *args.set]), tracker_options(flags)


def run(args) -> int:
    from flextrack.experiments import (  # the sim extra
        ablation,
        bound,
        common,
        euroc,
        filter_checks,
        table2,
        table2_vision,
        timing,
    )
    from flextrack.runners.cli_checks import numbers_problem, out_folder_problem
    from flextrack.runners.scoring import NothingScored

    problem = out_folder_problem(args.out)
    grid = args.experiment in ("table2", "bound")
    if grid and args.fps and not set(args.fps) <= set(paper.FPS):
        problem = f"--fps: choose among {list(paper.FPS)}, got {[f'{f:g}' for f in args.fps]}"
    if args.experiment == "euroc" and args.fps and len(args.fps) != 1:
        problem = "euroc --fps: give one frame rate"
    if args.jobs is not None and args.jobs < 1:
        problem = f"--jobs must be at least 1, got {args.jobs}"
    if args.data is not None and args.experiment not in ("euroc", "ablation"):
        problem = "--data applies to euroc and ablation (the others simulate their sequences)"
    if args.backend != "oracles" and args.experiment != "table2":
        problem = "--backend applies to table2 (the others run the noisy oracle)"
    if (args.tracker or args.set) and args.experiment != "euroc":
        problem = "--tracker and --set apply to euroc (table2, ablation and filter run their own variants)"
    if args.seeds < 1 or args.seed < 0:
        problem = f"--seeds must be at least 1 and --seed at least 0, got {args.seeds} and {args.seed}"
    problem = numbers_problem([("--duration", args.duration, 0, 3600), ("--backend-ms", args.backend_ms, 0, 60_000, True),
                               ("--object-distance", args.object_distance, 0, 100),
                               *(("--fps", f, 0, 1000) for f in args.fps or ())]) or problem
    if problem:
        print(f"flextrack experiment {args.experiment}: {problem}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    many = grid or args.experiment == "filter"
    seed_list = list(range(args.seed, args.seed + args.seeds)) if many else [args.seed]
    if args.experiment == "timing":
        args.in_process = True  # a gRPC server's threads in this process would time the GIL, not the tracker
    if args.experiment == "bound" or (args.experiment == "table2" and args.backend == "oracles"):
        args.jobs = args.jobs or common.default_jobs()  # the provenance records how many ran at once
    record = of_args(args, command="flextrack experiment " + args.experiment, seed_list=seed_list)  # at the start
    fps = tuple(int(f) for f in args.fps) if args.fps and grid else None
    try:
        if args.experiment == "table2" and args.backend != "oracles":
            table2_vision.run(args.out, args.backend, seed_list, args.duration, fps or (30, 120),
                              config=args.config or table2_vision.DEFAULT_CONFIG, backend_ms=args.backend_ms)
        elif args.experiment == "table2":
            table2.run(args.out, seed_list, args.duration, args.in_process, fps or paper.FPS, jobs=args.jobs)
        elif args.experiment == "bound":
            bound.run(args.out, seed_list, args.duration, args.in_process, fps or paper.FPS, jobs=args.jobs)
        elif args.experiment == "ablation":
            ablation.run(args.out, args.seed, args.duration, in_process=args.in_process, data=args.data)
        elif args.experiment == "filter":
            filter_checks.run(args.out, seed_list, args.duration, args.in_process)
        elif args.experiment == "timing":
            timing.run(args.out, args.seed, args.duration, in_process=args.in_process)
        else:
            euroc.run(args.out, args.data or euroc.DEFAULT_DATA, args.seed, args.in_process,
                      fps=args.fps[0] if args.fps else euroc.FPS, tracker=custom_tracker(args),
                      object_distance_m=args.object_distance, object_position=args.object_position)
    except NothingScored as exc:
        print(f"flextrack experiment {args.experiment}: nothing scored ({args.out / 'euroc.md'}): {exc}",
              file=sys.stderr)
        return 1
    except (FileNotFoundError, ValueError) as exc:
        print(f"flextrack experiment {args.experiment}: {exc}", file=sys.stderr)
        return 2
    stem = args.experiment if args.experiment != "table2" or args.backend == "oracles" else f"table2_{args.backend}"
    if args.experiment != "filter":  # filter writes filter.json itself, rows included
        provenance_file = args.out / f"{stem}.json"
        record["wall_s"] = round(time.perf_counter() - started, 1)
        provenance_file.write_text(json.dumps({"provenance": record,
                                               "files": sorted(p.name for p in args.out.glob(f"{stem}*.*")
                                                               if p != provenance_file)}, indent=1) + "\n")
    report = args.out / f"{stem}.md"
    print(report.read_text())
    print(f"wrote {report} and its CSV/PNG files in {time.perf_counter() - started:.0f} s")
    return 0
