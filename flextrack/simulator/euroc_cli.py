"""`flextrack convert-euroc`: a EuRoC recording as a sequence folder with a virtual object."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--euroc", type=Path, default=None,
                        help="EuRoC folder (imu0.csv, groundtruth.csv, cam0/imu0 sensor yaml, or mav0/) (default: "
                             "shared/data/euroc_v1_02_medium beside the checkout, from any working folder, as "
                             "`experiment euroc` finds it)")
    parser.add_argument("--out", type=Path, required=True, help="sequence folder to write")
    parser.add_argument("--fps", type=float, default=None,
                        help="frame rate (default: cam0's rate_hz from its sensor yaml, e.g. 20 for EuRoC)")
    parser.add_argument("--object", default="default", help="'default' or the path of a BOP .ply model (mm)")
    parser.add_argument("--object-id", default=None, help="the object's id in the sequence (default: \"default\" or the .ply's stem)")
    parser.add_argument("--max-distance", type=float, default=3.0,
                        help="farthest camera-object distance that counts as seen, m (also capped where the "
                             "object's image box falls below the PIA's 1/100 of the frame)")
    parser.add_argument("--object-scale", type=float, default=4.0,
                        help="scale the object by this factor (a scaled copy of the model is written into the "
                             "sequence): the MAV flies 1-4 m from anything; 4 gives a 58 cm box that the PIA "
                             "accepts up to ~2.2 m in cam0")
    parser.add_argument("--object-distance", type=float, default=None, metavar="M",
                        help="place the object where the cameras look most at this working distance, m (default: "
                             "the distance, within the PIA's reach, that sees it whole in the most frames)")
    parser.add_argument("--object-position", type=xyz, default=None, metavar="X,Y,Z",
                        help="put the object's centre here, in the recording's world frame, m (default: placed "
                             "automatically, see --object-distance)")
    parser.add_argument("--frame-latency", type=float, default=None, metavar="MS",
                        help="how long after its timestamp the device's camera hands a frame to the app, ms, declared "
                             "in sequence.yaml for the replay (default: not declared, a phone's 50)")
    parser.add_argument("--no-plots", action="store_true", help="skip the trajectory / IMU pictures")


def xyz(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        if len(parts) != 3:
            raise ValueError
        x, y, z = (float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,Z in metres, got {text!r}") from None
    return x, y, z


def run(args: argparse.Namespace) -> int:
    from flextrack.experiments.euroc import DEFAULT_DATA  # one home for the default, resolved from this file
    from flextrack.formats.sequence import load
    from flextrack.runners.cli_checks import numbers_problem, out_folder_problem
    from flextrack.simulator.euroc_convert import convert_euroc
    from flextrack.simulator.plots import plot_sequence

    euroc = args.euroc or DEFAULT_DATA
    problem = numbers_problem([("--fps", args.fps, 0, 1000), ("--max-distance", args.max_distance, 0, 100),
                               ("--object-scale", args.object_scale, 0, 1000),
                               ("--object-distance", args.object_distance, 0, 100),
                               ("--frame-latency", args.frame_latency, 0, 999, True)]) or out_folder_problem(args.out)
    if not euroc.is_dir():
        problem = problem or (f"--euroc {euroc}: no such folder" + ("" if args.euroc else " (the default: the "
                              "shared data beside the checkout)") + "; give the folder of a EuRoC recording")
    if problem:
        print(f"flextrack convert-euroc: {problem}", file=sys.stderr)
        return 2
    try:
        root = convert_euroc(euroc, args.out, fps=args.fps,
                             object_path=None if args.object == "default" else args.object, object_id=args.object_id,
                             max_distance_m=args.max_distance, object_scale=args.object_scale,
                             object_position=args.object_position, object_distance_m=args.object_distance,
                             frame_latency_ms=args.frame_latency)
    except (ValueError, FileNotFoundError) as exc:
        print(f"flextrack convert-euroc: {exc}", file=sys.stderr)
        return 2
    seq = load(root)
    placement = seq.meta["placement"]
    d = placement["distance_m_min_median_max"]
    print(f"wrote {root}: {len(seq.frame_ids)} frames at {seq.meta['converter']['fps']:g} FPS, {len(seq.imu.t_ns)} "
          f"IMU samples ({seq.meta['converter']['imu']}); object ({placement['how']}) at "
          f"{','.join(f'{x:.3f}' for x in placement['centre_W'])} (world, m; --object-position to move it), seen "
          f"whole in {100 * placement['visible_fraction']:.0f}% of frames at {d[0]:.2f}..{d[2]:.2f} m "
          f"(median {d[1]:.2f})")
    if not args.no_plots:
        for path in plot_sequence(root):
            print(f"wrote {path}")
    return 0
