"""`flextrack train`: train the PVNet-style network on rendered views, export ONNX, evaluate.

    flextrack train pvnet --object default --out runs/pvnet_default [--steps --batch --size --seed --resume]
    flextrack train pvnet-eval --model runs/pvnet_default/pvnet.onnx --object default --out runs/eval
    flextrack train pvnet-quantize --model runs/pvnet_default/pvnet.onnx     # writes pvnet_int8.onnx beside it
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from flextrack import assets


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="task", required=True, metavar="TASK")
    p = sub.add_parser("pvnet", help="train on rendered views, then export ONNX and a loss plot",
                       description="Train the PVNet-style network (torch, CPU or CUDA) on views of the object "
                       "rendered on random backgrounds; writes a checkpoint, the views, pvnet.onnx and loss.png "
                       "to --out. Four hours or more on a 2-core CPU for a useful model (docs/pvnet.md).",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--object", default="default", help="'default' or a BOP .ply (mm)")
    p.add_argument("--out", required=True, type=Path, help="run folder (checkpoint, views, ONNX, plot)")
    p.add_argument("--steps", type=int, default=8000,
                   help="optimisation steps; at the default --batch about 55 minutes on this project's 2-core CPU "
                        "(--minutes stops it earlier)")
    p.add_argument("--batch", type=int, default=16, help="rendered patches per step")
    p.add_argument("--size", type=int, default=128, help="training patch side (network-input px, multiple of 16)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--views", type=int, default=4000, help="object-only renders to train from")
    p.add_argument("--minutes", type=float, default=55.0, help="wall-time budget for the optimisation")
    p.add_argument("--width", type=int, default=32, help="network channel width")
    p.add_argument("--turn-deg", type=float, default=45.0,
                   help="in-plane turn augmentation of the object, +- degrees (45: with the estimator's turned "
                        "crops, any camera roll; 180: the network alone)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--resume", action="store_true", help="continue from the run folder's checkpoint")
    p.add_argument("--init", type=Path, help="start from this checkpoint's network weights (same width and keypoint count)")

    e = sub.add_parser("pvnet-eval", help="evaluate an ONNX model on rendered frames never seen in training",
                       description="Run the pvnet estimator on rendered frames of the object in the simulator's "
                       "rooms (or on a BOP folder) and report how many poses are found, 2D < 5 px and ADD < 10 % "
                       "of the diameter; writes the figures and per-frame rows to --out.",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    from flextrack.training import evaluate

    evaluate.add_arguments(e)

    q = sub.add_parser("pvnet-quantize", help="write an int8 copy of an ONNX model for the searches on a CPU (3x faster)",
                       description="Quantise a PVNet ONNX model to int8 (static, QDQ), calibrated on the inputs the "
                       "pvnet estimator feeds the network on rendered frames of unseen rooms; check the result "
                       "with pvnet-eval before serving it (docs/pvnet.md, Speed).",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    from flextrack.training import quantize

    quantize.add_arguments(q)


def _train(args) -> int:
    from tqdm import tqdm

    from estimators.objects import load_object
    from flextrack.training.export_onnx import export_checkpoint
    from flextrack.training.pvnet_train import TrainConfig, plot_loss, train

    if args.size % 16 or args.size < 32:
        print(f"--size must be a multiple of 16 and >= 32, got {args.size}", file=sys.stderr)
        return 2
    model_path = assets.object_model(args.object)
    obj = load_object(model_path.stem, model_path)
    cfg = TrainConfig(steps=args.steps, batch=args.batch, size=args.size, seed=args.seed, views=args.views,
                      minutes=args.minutes, width=args.width, threads=args.threads,
                      turn_deg=args.turn_deg)
    t0 = time.time()
    ckpt = train(obj, args.out, cfg, resume=args.resume, tqdm=tqdm, init=args.init)
    log = json.loads((args.out / "log.json").read_text())
    plot_loss(log["history"], args.out / "loss.png")
    onnx_path = args.out / "pvnet.onnx"
    diff = export_checkpoint(ckpt, onnx_path)
    print(f"trained {log['step']} steps in {log['elapsed_s'] / 60:.1f} min (this call {(time.time() - t0) / 60:.1f} min); "
          f"checkpoint {ckpt}; ONNX {onnx_path} ({onnx_path.stat().st_size / 1e6:.1f} MB, "
          f"onnxruntime vs torch max |diff| {diff:.2e}); loss plot {args.out / 'loss.png'}")
    return 0


def run(args) -> int:
    try:
        if args.task == "pvnet":
            return _train(args)
        if args.task == "pvnet-quantize":
            from flextrack.training import quantize

            return quantize.run(args)
        from flextrack.training import evaluate

        return evaluate.run(args)
    except (FileNotFoundError, ValueError) as exc:
        print(f"flextrack train {args.task}: {exc}", file=sys.stderr)
        return 2
