"""`flextrack bench pvnet`: per-frame cost of the pvnet estimator on rendered frames, its accuracy on
the same frames, and its memory over frame shapes.

Frames of the default object in the simulator's room are JPEG-encoded as a client sends them;
each is decoded as the service decodes it, then estimated. Prints, at batch 1, the mean decode,
inference, voting, PnP and refinement time per frame (wall), the process's CPU time a frame, and
the accuracy (found, 2D error under 5 px, ADD under 10 % of the diameter): for whole frames (a
first pose, or after a loss) and for the crops the SDK sends once it tracks (client_sdk.crop, around
the true pose with a 1 deg / 5 mm prior covariance); then frames/s (decode included) per batch size.
The estimator as served (its whole-frame searches on the model's int8 copy, `search_model`
"auto") and a baseline (the float model throughout) take turns frame by frame, so that load from
elsewhere on the machine falls on both alike, and the bench prints the ratio of their CPU a frame
beside their accuracy. `--out` writes the figures with their provenance.
`--memory` prints the resident memory after frames of 640x480, 1280x960 and 2048x2048 instead.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

from flextrack import assets

DEFAULT_MODEL = assets.pvnet_model_path()
STAGES = ("decode", "inference", "voting", "pnp", "refine")
PRIOR_STD_DEG, PRIOR_STD_M = 1.0, 0.005  # the prior the crops are cut for: about a tracking filter's
SHAPES = ((640, 480), (1280, 960), (2048, 2048), (1280, 960), (2048, 2048))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="PVNet ONNX file for the default object")
    parser.add_argument("--search-model", default="auto",
                        help="the estimator's search_model: 'auto' (MODEL_int8.onnx beside the model where there "
                             "is one), 'same', or an ONNX file")
    parser.add_argument("--no-baseline", action="store_true",
                        help="skip the baseline (search_model 'same': the float model throughout) that otherwise "
                             "runs turn about on the same frames")
    parser.add_argument("--frames", type=int, default=32, help="rendered frames (cycled through)")
    parser.add_argument("--batches", default="1,2,4,8,16", help="batch sizes to time")
    parser.add_argument("--repeats", type=int, default=2, help="passes over the frames per batch size")
    parser.add_argument("--threads", type=int, default=1,
                        help="onnxruntime intra-op threads (0: its default, every core; 1: a service worker's)")
    parser.add_argument("--device", default="auto", choices=["auto", "cpu"], help="auto: CUDA when present")
    parser.add_argument("--out", type=Path, help="write the batch-1 figures and their provenance here (JSON)")
    parser.add_argument("--memory", action="store_true",
                        help="print the resident memory after frames of 640x480, 1280x960 and 2048x2048 instead")


def _frames(n: int):
    """(whole-frame image, its crop's image and Crop, T_gt) per rendered frame, JPEG 90 4:4:4 as the device sends."""
    from client_sdk.crop import crop_rect
    from flextrack import wire
    from flextrack.geometry.camera import PinholeCamera, bbox_corners
    from flextrack.runners.payload import frame_jpeg
    from flextrack.training.evaluate import rendered_frames
    from flextrack.v1 import pose_estimation_pb2 as pb

    corners = bbox_corners(_object().vertices)
    prior_cov = wire.diagonal_covariance(np.radians(PRIOR_STD_DEG), PRIOR_STD_M)
    camera = PinholeCamera.linemod()  # rendered_frames' camera
    out = []
    for _, rgb, _, T_gt, _ in rendered_frames(assets.default_object_model(), n, seed=7, scenes=1):
        whole = pb.Image(encoding=pb.Image.JPEG, data=frame_jpeg(rgb, 90), width=rgb.shape[1], height=rgb.shape[0])
        rect = crop_rect(camera, corners, T_gt, prior_cov) or (0, 0, camera.width, camera.height)
        x, y, w, h = rect
        cut = pb.Image(encoding=pb.Image.JPEG, data=frame_jpeg(rgb[y:y + h, x:x + w], 90), width=w, height=h)
        out.append((whole, cut, pb.Crop(x=x, y=y, width=w, height=h), T_gt))
    return out, camera


def _object():
    from estimators.objects import load_object

    return load_object("default", assets.default_object_model())


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() / 2 ** 20


def _memory(estimator, frames, camera) -> int:
    """RSS after frames of each shape: the 640x480 frame padded (reflected) to the shape, the camera kept."""
    import cv2

    from estimators.base import EstimateInput
    from flextrack.geometry.camera import PinholeCamera
    from service.request_decoding import decode_image

    rgb = decode_image(frames[0][0], camera)
    estimator.estimate(EstimateInput(frame_id=0, capture_time_ns=0, camera=camera, image=rgb))
    base = _rss_mb()
    print(f"RSS after one 640x480 frame: {base:.0f} MB")
    for i, (w, h) in enumerate(SHAPES):
        big = cv2.copyMakeBorder(rgb, 0, h - rgb.shape[0], 0, w - rgb.shape[1], cv2.BORDER_REFLECT)
        cam = PinholeCamera(camera.fx, camera.fy, camera.cx, camera.cy, w, h)
        t = time.process_time()
        out = estimator.estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=cam, image=big))
        print(f"after a {w}x{h} frame ({out.status.name}, {(time.process_time() - t) * 1e3:.0f} ms CPU): RSS "
              f"{_rss_mb():.0f} MB ({_rss_mb() - base:+.0f} MB)")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS {peak:.0f} MB; RSS {_rss_mb() - base:+.0f} MB over the one 640x480 frame")
    return 0


def _batch1(estimators: dict, obj, frames, camera, cropped: bool) -> dict:
    """Per estimator, the batch-1 stage times, CPU a frame and accuracy over the frames, whole or as the SDK's
    crops; the estimators take turns frame by frame (the first goes first on even frames)."""
    from estimators.base import EstimateInput, Status
    from flextrack.geometry import metrics
    from flextrack.v1 import pose_estimation_pb2 as pb
    from service.request_decoding import decode_crop, decode_image

    runs = {name: {"stages": {k: [] for k in STAGES}, "proj": [], "add": [], "cpu": 0.0} for name in estimators}
    sizes = []
    for i, (whole, cut, crop, T_gt) in enumerate(frames):
        image = cut if cropped else whole
        sizes.append(len(image.data))
        for name in (list(estimators) if i % 2 == 0 else list(estimators)[::-1]):
            run = runs[name]
            c0, t = time.process_time(), time.perf_counter()
            cam = decode_crop(pb.EstimateRequest(image=cut, crop=crop), camera, np.zeros((0, 3)))[0] if cropped \
                else camera
            rgb = decode_image(image, cam)
            run["stages"]["decode"].append((time.perf_counter() - t) * 1e3)
            out = estimators[name].estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=cam, image=rgb))
            run["cpu"] += time.process_time() - c0
            for key in STAGES[1:]:
                run["stages"][key].append(out.stage_ms.get(key, 0.0))
            ok = out.status == Status.OK
            run["proj"].append(metrics.proj_px(out.T_CO, T_gt, camera, obj.vertices) if ok else np.inf)
            run["add"].append(metrics.add_m(out.T_CO, T_gt, obj.vertices) if ok else np.inf)
    n = len(frames)
    what = "crops as the SDK sends them" if cropped else "whole 640x480 frames"
    figures = {"frames": n, "median_request_kb": float(np.median(sizes)) / 1024, "models": {}}
    for name, run in runs.items():
        stages = {k: float(np.mean(v)) for k, v in run["stages"].items()}
        proj, add = np.array(run["proj"]), np.array(run["add"])
        f = {"stage_ms": stages, "sum_ms": sum(stages.values()), "cpu_ms": run["cpu"] / n * 1e3,
             "found": int(np.isfinite(proj).sum()), "proj_below_5px": float(np.mean(proj < 5)),
             "add_below_10pct": float(np.mean(add < 0.1 * obj.diameter_m))}
        figures["models"][name] = f
        print(f"batch 1, {what} (median {figures['median_request_kb']:.1f} kB), {name}, mean ms per frame: "
              + ", ".join(f"{k} {v:.2f}" for k, v in stages.items()) + f", sum {f['sum_ms']:.2f}; "
              f"CPU {f['cpu_ms']:.1f} ms a frame; accuracy: found {f['found']}/{n}, "
              f"2D < 5 px {100 * f['proj_below_5px']:.0f} %, ADD < 10 % of the diameter {100 * f['add_below_10pct']:.0f} %")
    if len(runs) == 2:
        served, base = figures["models"].values()
        figures["cpu_ratio"] = served["cpu_ms"] / base["cpu_ms"]
        first, second = runs
        print(f"  {first} / {second}: CPU a frame x{figures['cpu_ratio']:.2f}, "
              f"sum x{served['sum_ms'] / base['sum_ms']:.2f} (the same frames, turn about)")
    return figures


def run(args) -> int:
    from estimators.base import EstimateInput
    from estimators.objects import ObjectRegistry
    from estimators.pvnet import PvnetEstimator
    from flextrack.provenance import of_args
    from service.request_decoding import decode_image

    if not args.model.is_file():
        print(f"bench pvnet: model {args.model} not found (train one with `flextrack train pvnet`)", file=sys.stderr)
        return 2
    obj = _object()
    registry = ObjectRegistry([obj])
    try:
        estimator = PvnetEstimator(registry, args.model, device=args.device, threads=args.threads,
                                   search_model=args.search_model)
    except (FileNotFoundError, ValueError) as exc:
        print(f"bench pvnet: {exc}", file=sys.stderr)
        return 2
    frames, camera = _frames(args.frames)
    if args.memory:
        return _memory(estimator, frames, camera)
    served = f"searches on {estimator.search_model_path.name}"
    estimators = {served: estimator}
    if not args.no_baseline and estimator.search_model_path != args.model:
        estimators["float throughout (baseline)"] = PvnetEstimator(
            registry, args.model, device=args.device, threads=args.threads, search_model="same")
    print(f"pvnet bench: {args.model} ({served}) on {estimator.providers[0]}, {args.threads or 'default'} "
          f"intra-op thread(s), {len(frames)} rendered 640x480 frames (JPEG 90, 4:4:4)")

    def decode(i):
        return EstimateInput(frame_id=i, capture_time_ns=0, camera=camera,
                             image=decode_image(frames[i % len(frames)][0], camera))

    for e in estimators.values():
        e.estimate(decode(0))  # warm-up
    results = {"whole": _batch1(estimators, obj, frames, camera, cropped=False),
               "crops": _batch1(estimators, obj, frames, camera, cropped=True)}
    best = (0, 0.0)
    for b in [int(x) for x in args.batches.split(",") if x]:
        n = max(b, args.repeats * len(frames) // b * b)
        t = time.perf_counter()
        for start in range(0, n, b):
            estimator.estimate_batch([decode(i) for i in range(start, start + b)])
        fps = n / (time.perf_counter() - t)
        best = max(best, (fps, b))
        print(f"batch {b:>2}: {fps:6.1f} frames/s ({1e3 / fps:.1f} ms per frame, decode included)")
    if best[1]:
        print(f"best: batch {best[1]} at {best[0]:.1f} frames/s")
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        results["load_average"] = list(os.getloadavg())
        results["provenance"] = of_args(args, command="flextrack bench pvnet")
        args.out.write_text(json.dumps(results, indent=1))
        print(f"wrote {args.out}")
    return 0
