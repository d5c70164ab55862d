"""`flextrack bench pvnet`: per-frame cost of the pvnet estimator on rendered frames.

Frames of the default object in the simulator's room are JPEG-encoded as a client sends them;
each is decoded as the service decodes it, then estimated. Prints the mean decode, inference,
voting, PnP and refinement time per frame at batch 1, and frames/s (decode included) per batch size.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from flextrack import assets

DEFAULT_MODEL = assets.pvnet_model_path()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="PVNet ONNX file for the default object")
    parser.add_argument("--frames", type=int, default=32, help="rendered frames (cycled through)")
    parser.add_argument("--batches", default="1,2,4,8,16", help="batch sizes to time")
    parser.add_argument("--repeats", type=int, default=2, help="passes over the frames per batch size")
    parser.add_argument("--threads", type=int, default=0, help="onnxruntime intra-op threads (0: its default)")
    parser.add_argument("--device", default="auto", choices=["auto", "cpu"], help="auto: CUDA when present")


def _frames(n: int):
    from flextrack.geometry.camera import PinholeCamera
    from flextrack.runners.payload import frame_jpeg
    from flextrack.training.evaluate import rendered_frames
    from flextrack.v1 import pose_estimation_pb2 as pb

    out = []
    for _, rgb, camera, _, _ in rendered_frames(assets.default_object_model(), n, seed=7, scenes=1):
        out.append(pb.Image(encoding=pb.Image.JPEG, data=frame_jpeg(rgb, 90), width=rgb.shape[1], height=rgb.shape[0]))
    return out, PinholeCamera.linemod()


def run(args) -> int:
    from estimators.base import EstimateInput
    from estimators.objects import ObjectRegistry, load_object
    from estimators.pvnet import PvnetEstimator
    from service.request_decoding import decode_image

    if not args.model.is_file():
        print(f"bench pvnet: model {args.model} not found (train one with `flextrack train pvnet`)")
        return 2
    registry = ObjectRegistry([load_object("default", assets.default_object_model())])
    estimator = PvnetEstimator(registry, args.model, device=args.device, threads=args.threads)
    images, camera = _frames(args.frames)
    print(f"pvnet bench: {args.model} on {estimator.providers[0]}, {len(images)} rendered 640x480 JPEG frames")

    def decode(i):
        t = time.perf_counter()
        rgb = decode_image(images[i % len(images)], camera)
        return EstimateInput(frame_id=i, capture_time_ns=0, camera=camera, image=rgb), (time.perf_counter() - t) * 1e3

    estimator.estimate(decode(0)[0])  # warm-up
    stages = {"decode": [], "inference": [], "voting": [], "pnp": [], "refine": []}
    for i in range(len(images)):
        inp, ms = decode(i)
        out = estimator.estimate(inp)
        stages["decode"].append(ms)
        for key in ("inference", "voting", "pnp", "refine"):
            stages[key].append(out.stage_ms.get(key, 0.0))
    total = sum(np.mean(v) for v in stages.values())
    print("batch 1, mean ms per frame: " + ", ".join(f"{k} {np.mean(v):.2f}" for k, v in stages.items())
          + f", sum {total:.2f}")
    best = (0, 0.0)
    for b in [int(x) for x in args.batches.split(",")]:
        n = max(b, args.repeats * len(images) // b * b)
        t = time.perf_counter()
        for start in range(0, n, b):
            estimator.estimate_batch([decode(i)[0] for i in range(start, start + b)])
        fps = n / (time.perf_counter() - t)
        best = max(best, (fps, b))
        print(f"batch {b:>2}: {fps:6.1f} frames/s ({1e3 / fps:.1f} ms per frame, decode included)")
    print(f"best: batch {best[1]} at {best[0]:.1f} frames/s")
    return 0
