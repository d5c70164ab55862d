"""`flextrack simulate`: write a synthetic sequence folder (and its pictures, and frames on demand)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from flextrack.simulator.imu import PROFILES
from flextrack.simulator.trajectory import LEVELS, MOTIONS

# What a sequence folder can hold and a machine can write: an hour, 1000 FPS (the paper: 30-240), 10 kHz IMU.
MAX_DURATION_S, MAX_FPS, MAX_IMU_RATE = 3600.0, 1000.0, 10_000.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--motion", choices=MOTIONS, default="translational",
                        help="motion program (Table 3); 'static' holds the device still (Allan deviation)")
    parser.add_argument("--level", choices=LEVELS, default="easy", help="the program's speed level (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=30.0, help="seconds of motion after the still period")
    parser.add_argument("--fps", type=float, default=120.0, help="camera frame rate")
    parser.add_argument("--imu-rate", type=float, default=200.0, help="IMU sample rate, Hz")
    parser.add_argument("--seed", type=int, default=0, help="seeds the shake, IMU noise, object heading and room")
    parser.add_argument("--object", default="default", help="'default' or the path of a BOP .ply model (mm)")
    parser.add_argument("--object-id", default=None, help="object id in the sequence (default: 'default' or the file stem)")
    parser.add_argument("--imu-profile", choices=sorted(PROFILES), default="pixel2",
                        help="IMU noise and biases: a Pixel 2, EuRoC's ADIS16448, or none (default: %(default)s)")
    parser.add_argument("--imu-jitter", type=float, default=0.0, help="std of the IMU sampling instants, s (at most half the IMU period)")
    parser.add_argument("--still", type=float, default=2.0, help="seconds held still at the start (>= 1)")
    parser.add_argument("--moving-start", action="store_true", help="the first frame comes 1 s after the motion "
                        "reached full speed: a tracker starts on a moving device")
    parser.add_argument("--imu-time-offset", type=float, default=0.0, metavar="S",
                        help="the IMU stamps its samples S seconds late (camera-IMU time offset) (default: 0)")
    parser.add_argument("--render", action="store_true", help="render every frame now (rgb/, mask/, depth/)")
    parser.add_argument("--no-plots", action="store_true", help="skip the trajectory / IMU pictures")
    parser.add_argument("--out", type=Path, required=True, help="sequence folder to write")


def run(args: argparse.Namespace) -> int:
    from flextrack.runners.cli_checks import numbers_problem, out_folder_problem
    from flextrack.simulator.generate import generate_sequence
    from flextrack.simulator.plots import plot_sequence

    problem = numbers_problem([
        ("--duration", args.duration, 0, MAX_DURATION_S), ("--fps", args.fps, 0, MAX_FPS),
        ("--imu-rate", args.imu_rate, 0, MAX_IMU_RATE), ("--still", args.still, 1, MAX_DURATION_S, True),
        ("--imu-jitter", args.imu_jitter, 0, 0.5 / args.imu_rate if args.imu_rate > 0 else 0, True),
        ("--imu-time-offset", args.imu_time_offset, -1, 1, True)]) or out_folder_problem(args.out)
    if problem:
        print(f"flextrack simulate: {problem}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    try:
        root = generate_sequence(
            args.motion, args.level, args.out, duration_s=args.duration, fps=args.fps, imu_rate=args.imu_rate,
            seed=args.seed, object_path=None if args.object == "default" else args.object,
            object_id=args.object_id, imu_profile=args.imu_profile, imu_jitter_s=args.imu_jitter,
            still_s=args.still, moving_start=args.moving_start, imu_time_offset_s=args.imu_time_offset)
    except (ValueError, FileNotFoundError) as exc:
        print(f"flextrack simulate: {exc}", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - start
    from flextrack.formats.sequence import load
    seq = load(root)
    print(f"wrote {root}: {len(seq.frame_ids)} frames at {args.fps:g} FPS, {len(seq.imu.t_ns)} IMU samples "
          f"at {args.imu_rate:g} Hz ({args.imu_profile}) in {elapsed:.2f} s")
    _print_statistics(seq.meta.get("statistics", {}))
    if args.render:
        from flextrack.simulator.frames import render_sequence
        start = time.perf_counter()
        n = render_sequence(root, progress=True)
        print(f"rendered {n} frames in {time.perf_counter() - start:.1f} s")
    if not args.no_plots:
        for path in plot_sequence(root):
            print(f"wrote {path}")
    return 0


def _print_statistics(stats: dict) -> None:
    if "table3" not in stats:
        return
    rows = (("avg speed m/s", "avg_speed_m_s"), ("accel range m/s^2", "accel_range_m_s2"),
            ("avg angular rate rad/s", "avg_angular_rate_rad_s"), ("ang. accel range rad/s^2", "angular_accel_range_rad_s2"))
    fmt = lambda v: f"[{v[0]:.3f}, {v[1]:.3f}]" if isinstance(v, list) else f"{v:.3f}"
    print(f"{'':26s}{'Table 3':>18s}{'scripted':>18s}{'with shake':>18s}")
    for label, key in rows:
        print(f"{label:26s}{fmt(stats['table3'][key]):>18s}{fmt(stats['scripted'][key]):>18s}"
              f"{fmt(stats['with_shake'][key]):>18s}")
    print(f"({stats['note']})")
