"""`flextrack calibrate imu --data DIR`: what a recording's IMU does, against its ground truth (`calibration.imu`)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="what", metavar="WHAT", required=True)
    imu = sub.add_parser("imu", help="the IMU's noise densities, bias walk, camera-IMU time offset and lever arm "
                         "from a recording with motion-capture truth (EuRoC layout)")
    imu.add_argument("--data", type=Path, required=True,
                     help="the recording: imu0.csv and groundtruth.csv (EuRoC columns; flat as shared/data's or "
                     "under mav0/), with imu0_sensor.yaml to compare with when present")
    imu.add_argument("--json", type=Path, default=None, help="also write the findings and their provenance here")


def run(args: argparse.Namespace) -> int:
    from flextrack import provenance
    from flextrack.calibration.imu import GLITCH, calibrate
    from flextrack.formats import kalibr

    if not args.data.is_dir():
        print(f"flextrack calibrate imu: {args.data} is not a folder", file=sys.stderr)
        return 2
    try:
        found = calibrate(args.data)
    except (FileNotFoundError, ValueError) as exc:
        print(f"flextrack calibrate imu: {exc}", file=sys.stderr)
        return 2
    yaml = next((p for p in (args.data / "imu0_sensor.yaml", args.data / "mav0" / "imu0" / "sensor.yaml")
                 if p.is_file()), None)
    stated = kalibr.read_imu_sensor(yaml)[0] if yaml else None
    lines = [
        (f"{args.data}: {found.rate_hz:.1f} Hz median, {found.gaps} gaps over 5 intervals (longest "
        f"{found.longest_gap_s:.3f} s), {found.still_s:.1f} s still"),
        (f"time offset (t_imu = t_camera + offset), gyro vs the truth's rate: {found.time_offset_ms:.2f} ms "
         f"(peak correlation {found.time_offset_peak:.2f})" if found.time_offset_ms == found.time_offset_ms else
         "time offset: the gyro against the truth's rate shows no clear peak within +-200 ms (the rest taken at 0)"),
        f"white noise from {'still stretches' if found.noise_from == 'still' else 'residuals against the truth (an upper bound)'}:"
        f" gyro {found.gyroscope_noise_density:.3g} rad/s/sqrt(Hz), accel {found.accelerometer_noise_density:.3g} "
        "m/s^2/sqrt(Hz)" + (f" (yaml: {stated.gyroscope_noise_density:.3g}, {stated.accelerometer_noise_density:.3g})"
                            if stated else ""),
        f"gyro bias walk: {found.gyroscope_random_walk:.3g} rad/s^2/sqrt(Hz)"
        + (f" (yaml: {stated.gyroscope_random_walk:.3g})" if stated else ""),
        (f"gyro minus the truth's rate: {found.gyro_residual_rms:.3f} rad/s RMS; accelerometer minus the truth's "
        f"specific force: {found.accel_residual_rms:.3f} m/s^2 RMS, {found.accel_residual_rms_lever:.3f} with a lever "
        f"arm of ({', '.join(f'{1000 * x:.1f}' for x in found.lever_arm_m)}) mm"),
        (f"the truth jumped where the gyro did not (|gyro - its rate| over {GLITCH:g}x the median) at "
         f"{len(found.truth_jumps)} moments" + (f", s from the start: {', '.join(f'{x:.1f}' for x in found.truth_jumps[:12])}"
                                                 f"{' ...' if len(found.truth_jumps) > 12 else ''}" if found.truth_jumps else "")),
    ]
    print("\n".join(lines))
    if args.json:
        record = provenance.provenance(command="flextrack calibrate imu", data=args.data)
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"provenance": record, "imu": found.as_dict()}, indent=1) + "\n")
        print(f"wrote {args.json}")
    return 0
