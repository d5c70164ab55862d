"""Per-call timing of the tracker core: PIM (PIA in add_frame), PRM (on_backend_response with BSCM and
the re-propagation of ~50 ms of IMU at 200 Hz) and PPM (add_imu, per IMU sample).

A body circles a box at 0.6 m with constant rates; the backend answers with the exact pose 50 ms
after each frame. Each operation is timed per call with `time.perf_counter_ns`; the figures are the
median and the 99th percentile in microseconds, raw and stretched by the device slowdown (the paper's
Pixel 2 factor 3185 / 1294 = 2.46). `run(args)` prints a table; `measure(...)` returns the rows.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from client_sdk import ResponseOutcome, Tracker, TrackerOptions
from flextrack.geometry import se3, so3
from flextrack.geometry.camera import PinholeCamera, bbox_corners

PAPER_MS = {"PIM": 0.35, "PRM": 0.86, "PPM": None}
PIXEL2_SLOWDOWN = 3185 / 1294
_G = np.array([0.0, 0.0, -9.81])


def _body(t: float, rate: float = 0.4, radius: float = 0.6) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(T_OB, gyro, accel) of a body on a circle around the origin, looking at it."""
    psi = rate * t
    R = so3.exp(np.array([0.0, 0.0, psi])) @ np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    p = radius * np.array([np.cos(psi), np.sin(psi), 0.0])
    a_O = -rate * rate * p
    return se3.make(R, p), R.T @ np.array([0.0, 0.0, rate]), R.T @ (a_O - _G)


def measure(seconds: float = 20.0, imu_hz: float = 200.0, fps: float = 60.0, latency_s: float = 0.05,
            integrator: str = "paper") -> dict[str, np.ndarray]:
    """Per-call times in ns of PIM (inspection inside add_frame), add_frame, PRM and PPM."""
    camera = PinholeCamera.linemod()
    box = bbox_corners(np.array([[-0.05, -0.04, -0.03], [0.05, 0.04, 0.03]]))
    T_BC = np.eye(4)
    # the body moves from the start: initialise without the stillness check (timing only)
    tracker = Tracker(TrackerOptions(integrator=integrator, init_require_still=False), camera, T_BC, box)
    dt_imu, dt_frame, lat = int(1e9 / imu_hz), int(1e9 / fps), int(latency_s * 1e9)
    imu_t = np.arange(1, int(seconds * imu_hz)) * dt_imu
    imu = [(int(t),) + _body(t * 1e-9)[1:] for t in imu_t]
    times: dict[str, list[int]] = {"PIM": [], "add_frame": [], "PRM": [], "PPM": []}
    inspector = tracker.inspector
    clock = time.perf_counter_ns
    pending, next_frame, last_uv, frame_fps = None, dt_frame // 2, None, fps
    for t, w, f in imu:
        w, f = w.tolist(), f.tolist()
        if pending is not None and pending[0] <= t:
            _, rid, cap = pending
            T_CO = se3.inverse(_body(cap * 1e-9)[0] @ T_BC)
            c0 = clock()
            outcome = tracker.on_backend_response(rid, cap, T_CO, True)
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
                # the PIA part of add_frame, on the same pose, timed on its own
                c2 = clock()
                uv = inspector.project(r.T_CO)
                inspector.inspect(uv, last_uv, frame_fps)
                c3 = clock()
                times["PIM"].append(c3 - c2)
                last_uv = uv
            if r.request is not None:
                pending = (r.request.frame_t_ns + lat, r.request.request_id, r.request.frame_t_ns)
            next_frame += dt_frame
    return {k: np.array(v, dtype=float) for k, v in times.items()}


def rows(times: dict[str, np.ndarray], slowdown: float = PIXEL2_SLOWDOWN) -> list[dict]:
    out = []
    for name, ns in times.items():
        med, p99 = float(np.median(ns)) / 1e3, float(np.percentile(ns, 99)) / 1e3
        out.append({"operation": name, "calls": len(ns), "median_us": med, "p99_us": p99,
                    "stretched_median_us": med * slowdown, "paper_ms": PAPER_MS.get(name)})
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--seconds", type=float, default=20.0, help="simulated seconds of IMU (200 Hz)")
    parser.add_argument("--fps", type=float, default=60.0)
    parser.add_argument("--latency-ms", type=float, default=50.0, help="backend answer delay (IMU re-propagated)")
    parser.add_argument("--integrator", choices=("paper", "midpoint"), default="paper")
    parser.add_argument("--slowdown", type=float, default=PIXEL2_SLOWDOWN, help="device slowdown factor")


def run(args: argparse.Namespace) -> int:
    times = measure(args.seconds, fps=args.fps, latency_s=args.latency_ms / 1e3, integrator=args.integrator)
    print(f"tracker core timing: {args.seconds:g} s of IMU at 200 Hz, {args.fps:g} FPS, "
          f"{args.latency_ms:g} ms backend latency, integrator {args.integrator}")
    print(f"{'operation':<10} {'calls':>6} {'median_us':>10} {'p99_us':>9} {'x' + format(args.slowdown, '.2f'):>9} "
          f"{'paper_ms':>9}")
    for r in rows(times, args.slowdown):
        paper = "" if r["paper_ms"] is None else f"{r['paper_ms']:.2f}"
        print(f"{r['operation']:<10} {r['calls']:>6} {r['median_us']:>10.1f} {r['p99_us']:>9.1f} "
              f"{r['stretched_median_us']:>9.1f} {paper:>9}")
    return 0


if __name__ == "__main__":
    p = argparse.ArgumentParser(description=__doc__)
    add_arguments(p)
    raise SystemExit(run(p.parse_args()))
