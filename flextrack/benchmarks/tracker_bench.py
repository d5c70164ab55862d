"""The tracker core's figures: per-call timing of PIM, PRM and PPM, and accuracy per configuration.

Timing: the analytic world of `flextrack.testing.tracker_world` (a body circling a box at 1.2 m, 200 Hz
IMU, a ground-truth backend answering 50 ms after each request, so each PRM call re-propagates
~50 ms of IMU). Each operation is timed per call with `time.perf_counter_ns`: PIM = the PIA part of
`add_frame` (projection, area, offset, decision), add_frame = all of it (pose at the frame, PIA,
request decision), PRM = `on_backend_response` (state reset, BSCM, re-propagation), PPM = `add_imu`.
Figures are the median and the 99th percentile in microseconds, raw and stretched by the device
slowdown (the paper's Pixel 2 factor 3185 / 1294 = 2.46).

Accuracy (`--accuracy`): the two integrators on exact IMU, then mean position mm / orientation deg /
2D px over `--seconds` in the same world with the paper's IMU noise and consumer biases, GT and
Noisy (3 mm, 0.3 deg per axis) backends, for the paper method's defaults and the variants
docs/tracker.md discusses. Both tables are the paper's method (`fusion = "paper"`): integrators, gains
and BSCM are its options; the filter has its own figures (`flextrack experiment filter`).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from client_sdk import ResponseOutcome, TrackerOptions, create_tracker
from flextrack.geometry import se3, so3
from flextrack.geometry.metrics import proj_px, re_deg, te_mm
from flextrack.runners.cli_checks import deprecated_alias
from flextrack.testing.tracker_world import BOX_O, CAMERA, T_BC, Motion, drive

PAPER_MS = {"PIM": 0.35, "PRM": 0.86}
PIXEL2_SLOWDOWN = 3185 / 1294


def measure(seconds: float = 20.0, imu_hz: float = 200.0, fps: float = 60.0, latency_s: float = 0.05,
            integrator: str = "paper", fusion: str = "filter") -> dict[str, np.ndarray]:
    """Per-call times in ns of PIM (inspection inside add_frame), add_frame, PRM and PPM."""
    m = Motion()
    tracker = create_tracker(TrackerOptions(integrator=integrator, fusion=fusion), CAMERA, T_BC, BOX_O)
    covariance = np.diag([np.radians(0.3) ** 2] * 3 + [0.003 ** 2] * 3)  # the noisy oracle's, as the filter gets it
    dt_imu, dt_frame, lat = round(1e9 / imu_hz), round(1e9 / fps), round(latency_s * 1e9)
    imu = [(int(t),) + tuple(v.tolist() for v in m.imu(t * 1e-9)) for t in np.arange(1, int(seconds * imu_hz)) * dt_imu]
    times: dict[str, list[int]] = {"PIM": [], "add_frame": [], "PRM": [], "PPM": []}
    inspector, clock = tracker.inspector, time.perf_counter_ns
    pending, next_frame, last_uv = None, dt_frame // 2, None
    for t, w, f in imu:
        if pending is not None and pending[0] <= t:
            _, rid, cap = pending
            T_CO = m.T_CO(cap * 1e-9)
            c0 = clock()
            outcome = tracker.on_backend_response(rid, cap, T_CO, True, covariance)
            c1 = clock()
            if outcome is ResponseOutcome.APPLIED:
                times["PRM"].append(c1 - c0)
            pending = None
        c0 = clock()
        tracker.add_imu(t, w, f)
        c1 = clock()
        if tracker.initialized:
            times["PPM"].append(c1 - c0)
        if next_frame <= t:
            c0 = clock()
            r = tracker.add_frame(next_frame)
            c1 = clock()
            if r.T_CO is not None:
                times["add_frame"].append(c1 - c0)
                c2 = clock()  # the PIA part of add_frame, on the same pose, timed on its own
                uv = inspector.project(r.T_CO)
                inspector.inspect(uv, last_uv, fps)
                c3 = clock()
                times["PIM"].append(c3 - c2)
                last_uv = uv
            if r.request is not None:
                pending = (r.request.frame_t_ns + lat, r.request.request_id, r.request.frame_t_ns)
            next_frame += dt_frame
    return {k: np.array(v, dtype=float) for k, v in times.items()}


def timing_rows(times: dict[str, np.ndarray], slowdown: float = PIXEL2_SLOWDOWN) -> list[dict]:
    out = []
    for name, ns in times.items():
        med, p99 = float(np.median(ns)) / 1e3, float(np.percentile(ns, 99)) / 1e3
        out.append({"operation": name, "calls": len(ns), "median_us": med, "p99_us": p99,
                    "stretched_median_us": med * slowdown, "paper_ms": PAPER_MS.get(name)})
    return out


ACCURACY_CONFIGS = {
    "paper method, defaults": {},
    "paper gains (1, 1, 1)": {"gyro_bias_gain": 1.0, "accel_bias_gain": 1.0, "velocity_gain": 1.0},
    "V_avg from backend p_OB (paper)": {"bscm_imu_orientation": False},
    "pose_gain 0.5": {"pose_gain": 0.5},
    "midpoint integrator": {"integrator": "midpoint"},
    "BSCM off": {"bscm": False},
    "BSCM + PIA off": {"bscm": False, "pia": False},
}


def accuracy(seconds: float = 20.0, seed: int = 1) -> list[tuple[str, list[np.ndarray]]]:
    """Per config: mean (mm, deg, px, max px) for GT 30, GT 120, Noisy 30, Noisy 120 FPS."""
    m = Motion()
    imu = {"b_g": (0.005, -0.01, 0.0075), "b_a": (0.025, -0.04, 0.05),
           "gyro_sigma": 6.63e-5 * np.sqrt(200), "accel_sigma": 7.35e-4 * np.sqrt(200)}
    out = []
    for name, kw in ACCURACY_CONFIGS.items():
        cells = []
        for noisy in (False, True):
            for fps in (30.0, 120.0):
                rng = np.random.default_rng(seed)

                def answer(t, rng=rng):
                    T = m.T_CO(t)
                    return se3.make(so3.exp(np.radians(0.3) * rng.standard_normal(3)) @ T[:3, :3],
                                    T[:3, 3] + 0.003 * rng.standard_normal(3))

                run = drive(m, TrackerOptions(fusion="paper", **kw), duration_s=seconds, fps=fps, seed=seed,
                            answer=answer if noisy else None, **imu)
                e = np.array([(te_mm(T, G), re_deg(T, G), proj_px(T, G, CAMERA, BOX_O))
                              for t, T in zip(run.times_ns, run.poses) if T is not None
                              for G in [m.T_CO(t * 1e-9)]])
                cells.append(np.array([*e.mean(axis=0), e[:, 2].max()]))
        out.append((name, cells))
    return out


def integrator_comparison() -> list[tuple[str, tuple, tuple]]:
    """Per integrator: (mm, deg, px) after ~3 s of IMU only from one backend pose, and (mean, max) px
    with a GT backend (50 ms latency, 60 FPS, 10 s); exact IMU, no biases."""
    m, out = Motion(), []
    for integrator in ("paper", "midpoint"):
        tr = drive(m, TrackerOptions(fusion="paper", integrator=integrator, backend_after_init=False),
                   duration_s=4.0).tracker
        T, G = tr.pose_at(tr.now_ns), m.T_CO(tr.now_ns * 1e-9)
        run = drive(m, TrackerOptions(fusion="paper", integrator=integrator), duration_s=10.0, fps=60.0)
        e = [proj_px(P, m.T_CO(t * 1e-9), CAMERA, BOX_O) for t, P in zip(run.times_ns, run.poses) if P is not None]
        out.append((integrator, (te_mm(T, G), re_deg(T, G), proj_px(T, G, CAMERA, BOX_O)),
                    (float(np.mean(e)), float(np.max(e)))))
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds")
    parser.add_argument("--fps", type=float, default=60.0, help="frame rate for the timing run")
    parser.add_argument("--latency-ms", type=float, default=50.0, help="backend answer delay (IMU re-propagated)")
    parser.add_argument("--integrator", choices=("paper", "midpoint"), default="paper",
                        help="the paper method's integrator (the filter always uses midpoint) (default: %(default)s)")
    parser.add_argument("--tracker", choices=("filter", "paper"), default="filter",
                        help="tracker core to time (default: %(default)s)")
    deprecated_alias(parser, "--fusion", "--tracker", choices=("filter", "paper"))
    parser.add_argument("--slowdown", type=float, default=PIXEL2_SLOWDOWN, help="device slowdown factor")
    parser.add_argument("--accuracy", action="store_true",
                        help="print the paper method's accuracy tables (integrators, gains, BSCM) instead of timing")


def run(args: argparse.Namespace) -> int:
    if not (args.fps > 0 and args.seconds > 0 and args.latency_ms >= 0 and args.slowdown > 0):
        print("flextrack bench tracker: --fps, --seconds and --slowdown must be > 0 and --latency-ms >= 0",
              file=sys.stderr)
        return 2
    if args.accuracy:
        print("| integrator | IMU only ~3 s: mm / deg / px | GT backend: mean / max px |")
        print("|---|---|---|")
        for name, imu_only, gt in integrator_comparison():
            print(f"| {name} | {imu_only[0]:.3f} / {imu_only[1]:.4f} / {imu_only[2]:.3f} | {gt[0]:.4f} / {gt[1]:.4f} |")
        print()
        print("| config | GT 30 FPS | GT 120 FPS | Noisy 30 FPS | Noisy 120 FPS |")
        print("|---|---|---|---|---|")
        for name, cells in accuracy(args.seconds):
            print(f"| {name} | " + " | ".join(f"{c[0]:.2f} / {c[1]:.2f} / {c[2]:.2f} (max {c[3]:.2f})"
                                             for c in cells) + " |")
        return 0
    times = measure(args.seconds, fps=args.fps, latency_s=args.latency_ms / 1e3, integrator=args.integrator,
                    fusion=args.tracker)
    print(f"tracker core timing: {args.seconds:g} s of IMU at 200 Hz, {args.fps:g} FPS, "
          f"{args.latency_ms:g} ms backend latency, tracker {args.tracker}, integrator {args.integrator}")
    print(f"| operation | calls | median us | p99 us | median x {args.slowdown:.2f} us | paper (stretched) ms |")
    print("|---|---|---|---|---|---|")
    for r in timing_rows(times, args.slowdown):
        paper = "" if r["paper_ms"] is None else f"{r['paper_ms']:.2f}"
        print(f"| {r['operation']} | {r['calls']} | {r['median_us']:.1f} | {r['p99_us']:.1f} | "
              f"{r['stretched_median_us']:.1f} | {paper} |")
    return 0


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_arguments(p)
    raise SystemExit(run(p.parse_args()))
