"""`flextrack bench region`: the region estimator's cost a frame, and the service's frame rate with it.

Frames of the default object in the simulator's room (640x480, JPEG as a device sends them), each
with a prior drawn around the truth (10 mm / 5 deg per axis by default), cut as the SDK cuts a
tracked frame (`client_sdk.crop`: the prior's box grown by 3 sigma and 24 px) unless `--whole`.
Two figures:

1. in-process: the CPU time a frame (process time), the JPEG decode included, median and p90, and
   the refinement's alone (the decode as the service does it: `decode_image` with `decode_crop`'s
   camera);
2. through a real gRPC server on loopback serving the default config: `--callers` closed-loop
   unary callers, each its own session, for `--seconds`; frames/s, the process's CPU a frame and the
   frames/s one core serves at that cost (callers and server share the process: an upper bound on
   the server's cost), latency p50/p99, and the share of answers under 5 px.

The first request builds (or reads from the cache) the viewpoint model; it is not timed. The load average at
the end is printed and stored with the figures: on a machine shared with other work CPU times rise.
"""

from __future__ import annotations

import argparse
import json
import os
import threading
import time
from pathlib import Path

import numpy as np

from flextrack import assets

PROJ_PX = 5.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--estimator", default="region", help="an estimator of the default config that takes a prior")
    parser.add_argument("--frames", type=int, default=24, help="rendered frames (cycled through)")
    parser.add_argument("--prior", default="10:5", help="prior sigma per axis, mm:deg")
    parser.add_argument("--callers", type=int, default=2, help="concurrent closed-loop callers through gRPC")
    parser.add_argument("--seconds", type=float, default=10.0, help="measuring time through gRPC")
    parser.add_argument("--seed", type=int, default=0, help="seeds the frames' priors")
    parser.add_argument("--whole", action="store_true",
                        help="send whole 640x480 frames instead of the SDK's crop around each prior")
    parser.add_argument("--out", type=Path, help="write the figures and their provenance here (JSON)")


def _frames(n: int, seed: int, sigma_m: float, sigma_rad: float, covariance: np.ndarray, whole: bool):
    """(JPEG bytes, T_CO truth, prior T_CO, crop (x, y, w, h) or None) per frame."""
    from client_sdk.crop import crop_rect
    from estimators.objects import load_object
    from flextrack.geometry import se3, so3
    from flextrack.runners.payload import frame_jpeg
    from flextrack.training.evaluate import rendered_frames

    corners = load_object("default", assets.default_object_model()).bbox_corners
    rng = np.random.default_rng(seed)
    out = []
    for _, rgb, camera, T, _ in rendered_frames(assets.default_object_model(), n, seed=7, scenes=1):
        d_theta, d_t = rng.normal(0, sigma_rad, 3), rng.normal(0, sigma_m, 3)
        prior = se3.make(so3.exp(-d_theta) @ T[:3, :3], T[:3, 3] - d_t)
        rect = None if whole else crop_rect(camera, corners, prior, covariance)
        if rect is not None:
            x, y, w, h = rect
            rgb = rgb[y:y + h, x:x + w]
        out.append((frame_jpeg(np.ascontiguousarray(rgb), 90), T, prior, rect))
    return out, camera


def _request(i: int, frame, camera, covariance, estimator: str, session: str):
    from flextrack import wire
    from flextrack.v1 import pose_estimation_pb2 as pb

    jpeg, _, prior, rect = frame
    w, h = (rect[2], rect[3]) if rect else (camera.width, camera.height)
    return pb.EstimateRequest(
        session_id=session, frame_id=i, capture_time_ns=i, estimator=estimator,
        image=pb.Image(encoding=pb.Image.JPEG, data=jpeg, width=w, height=h),
        crop=pb.Crop(x=rect[0], y=rect[1], width=w, height=h) if rect else None,
        intrinsics=wire.intrinsics_to_pb(camera),
        prior=pb.PosePrior(pose=wire.pose_to_pb(prior), covariance=wire.covariance_to_pb(covariance)))


def _in_process(registry, name: str, frames, camera, covariance) -> dict:
    from estimators.base import EstimateInput
    from service.request_decoding import decode_crop, decode_image

    estimator = registry.get(name)
    cpu_ms, refine_ms, kb = [], [], []
    for i, frame in enumerate(frames):
        request = _request(i, frame, camera, covariance, name, "bench")
        kb.append(len(request.image.data) / 1e3)
        t0 = time.process_time()
        seen, _ = decode_crop(request, camera, np.zeros((0, 3)))
        rgb = decode_image(request.image, seen)
        t1 = time.process_time()
        estimator.estimate(EstimateInput(frame_id=i, capture_time_ns=i, session_id="bench", camera=seen, image=rgb,
                                         prior_T_CO=frame[2], prior_covariance=covariance))
        t2 = time.process_time()
        cpu_ms.append((t2 - t0) * 1e3)
        refine_ms.append((t2 - t1) * 1e3)
    return {"cpu_ms_median": float(np.median(cpu_ms)), "cpu_ms_p90": float(np.percentile(cpu_ms, 90)),
            "refine_cpu_ms_median": float(np.median(refine_ms)), "refine_cpu_ms_p90": float(np.percentile(refine_ms, 90)),
            "frames": len(cpu_ms), "decode_included": True, "median_request_kb": float(np.median(kb)),
            "cropped": sum(f[3] is not None for f in frames)}


def _through_grpc(registry, name: str, frames, camera, covariance, callers: int, seconds: float) -> dict:
    import grpc

    from estimators.objects import load_object
    from flextrack import wire
    from flextrack.geometry import metrics
    from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc
    from service.server import BackgroundServer

    vertices = load_object("default", assets.default_object_model()).vertices
    latencies, errors, lock = [], [], threading.Lock()
    start = threading.Event()
    deadline = [0.0]

    def caller(k: int, address: str) -> None:
        with grpc.insecure_channel(address) as channel:
            stub = pb_grpc.PoseEstimationStub(channel)
            stub.Estimate(_request(0, frames[0], camera, covariance, name, f"bench-{k}"))  # session warm
            start.wait()
            i = k
            while time.perf_counter() < deadline[0]:
                frame = frames[i % len(frames)]
                t = time.perf_counter()
                answer = stub.Estimate(_request(i, frame, camera, covariance, name, f"bench-{k}"))
                ms = (time.perf_counter() - t) * 1e3
                px = (metrics.proj_px(wire.pose_from_pb(answer.pose), frame[1], camera, vertices)
                      if answer.status == answer.OK else float("inf"))
                with lock:
                    latencies.append(ms)
                    errors.append(px)
                i += callers

    with BackgroundServer(registry) as server:
        threads = [threading.Thread(target=caller, args=(k, server.address)) for k in range(callers)]
        for th in threads:
            th.start()
        time.sleep(0.5)  # the callers' warm-up requests are on their way; none is timed
        deadline[0] = time.perf_counter() + seconds
        t0, cpu0 = time.perf_counter(), time.process_time()
        start.set()
        for th in threads:
            th.join()
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    lat = np.array(latencies)
    cpu_ms = 1e3 * cpu / max(len(lat), 1)
    return {"frames_per_s": len(lat) / wall, "answers": len(lat), "process_cpu_ms_per_frame": cpu_ms,
            "frames_per_s_per_core": 1e3 / cpu_ms, "latency_ms_p50": float(np.median(lat)),
            "latency_ms_p99": float(np.percentile(lat, 99)),
            "share_proj_5px": float(np.mean(np.array(errors) < PROJ_PX)), "callers": callers, "seconds": seconds}


def run(args: argparse.Namespace) -> int:
    from estimators.registry import EstimatorRegistry
    from flextrack.provenance import of_args
    from flextrack.wire import diagonal_covariance

    mm, deg = (float(x) for x in args.prior.split(":"))
    registry = EstimatorRegistry.from_config(assets.default_config_path())
    if args.estimator not in registry.names():
        print(f"bench region: the default config serves {registry.names()}, not {args.estimator!r}")
        return 2
    covariance = diagonal_covariance(np.radians(deg), mm / 1e3)
    frames, camera = _frames(args.frames, args.seed, mm / 1e3, np.radians(deg), covariance, args.whole)
    what = "whole frames" if args.whole else "the SDK's crops of them"
    print(f"bench region: {args.estimator}, {len(frames)} rendered 640x480 frames ({what}, JPEG), "
          f"priors {mm:g} mm / {deg:g} deg")
    _in_process(registry, args.estimator, frames[:1], camera, covariance)  # the viewpoint model, built or read
    local = _in_process(registry, args.estimator, frames, camera, covariance)
    print(f"in-process: {local['cpu_ms_median']:.1f} ms CPU a frame (median), decode included, "
          f"{local['median_request_kb']:.0f} kB a request "
          f"(p90 {local['cpu_ms_p90']:.1f}); the refinement alone {local['refine_cpu_ms_median']:.1f} ms")
    served = _through_grpc(registry, args.estimator, frames, camera, covariance, args.callers, args.seconds)
    print(f"through gRPC, {args.callers} callers: {served['frames_per_s']:.1f} frames/s "
          f"({served['frames_per_s_per_core']:.1f} frames/s per core at {served['process_cpu_ms_per_frame']:.1f} ms "
          f"of the process's CPU a frame, callers included), latency p50 "
          f"{served['latency_ms_p50']:.1f} ms, p99 {served['latency_ms_p99']:.1f} ms; "
          f"{100 * served['share_proj_5px']:.1f} % of {served['answers']} answers under {PROJ_PX:g} px")
    load = list(os.getloadavg())  # CPU times rise on a machine shared with other work: the figures' context
    print("load average at the end (1, 5, 15 min): " + ", ".join(f"{x:.1f}" for x in load))
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"in_process": local, "grpc": served, "load_average": load,
                                        "provenance": of_args(args, command="flextrack bench region")}, indent=1))
        print(f"wrote {args.out}")
    return 0
