"""Quantise a PVNet ONNX model to int8 (static, QDQ) for the CPU, calibrated on the estimator's own inputs.

Why static and not dynamic: onnxruntime's dynamic quantisation turns each Conv into a ConvInteger
whose activations are quantised at run time, which on this network saves under a fifth; static
quantisation fixes the activations' ranges from calibration inputs and runs int8 convolutions
end to end, about 3.4 times faster than float on one core (docs/pvnet.md, Speed).

The calibration inputs are exactly what the estimator feeds the network (the reduced frame, the
full-resolution window, the zoomed crops), collected by running the float model's estimator on
rendered frames of the object in rooms of a seed that neither training (rooms 1000-1007), the
evaluation (20261122), its tuning frames (777) nor `flextrack bench pvnet` (7) uses. Per-channel
int8 weights, uint8 activations, min-max ranges. The quantised model keeps the float model's
metadata (the keypoints, the input scale, the output stride) and says what it was made from.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

CALIBRATION_SEED = 4242


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="the float PVNet ONNX file")
    parser.add_argument("--object", default="default", help="'default' or the BOP .ply (mm) the model was trained on")
    parser.add_argument("--out", type=Path, help="the int8 ONNX file to write (default: MODEL_int8.onnx beside the "
                        "model, which the pvnet estimator's searches then run on: its search_model \"auto\")")
    parser.add_argument("--frames", type=int, default=24, help="rendered calibration frames")
    parser.add_argument("--seed", type=int, default=CALIBRATION_SEED,
                        help="seed of the calibration frames (keep it off the training, evaluation and bench seeds)")


def calibration_inputs(model: Path, object_path: Path, frames: int, seed: int) -> list[np.ndarray]:
    """The network inputs (1, 3, H, W) float32 the float model's estimator runs on rendered frames, JPEG 90 as sent:
    on the whole frame, and on the crop around the object a tracking device sends."""
    from client_sdk.crop import crop_rect
    from estimators.base import EstimateInput
    from estimators.objects import ObjectRegistry, load_object
    from estimators.pvnet import PvnetEstimator
    from flextrack import wire
    from flextrack.geometry.camera import bbox_corners
    from flextrack.training.evaluate import as_sent, rendered_frames

    obj = load_object(object_path.stem, object_path)
    estimator = PvnetEstimator(ObjectRegistry([obj]), model, device="cpu", threads=1, search_model="same")
    seen: list[np.ndarray] = []
    run = estimator._run

    def record(images, search=False):
        seen.extend(np.stack([im]).astype(np.float32).transpose(0, 3, 1, 2) / np.float32(255.0) for im in images)
        return run(images, search)

    estimator._run = record
    corners = bbox_corners(obj.vertices)
    prior_cov = wire.diagonal_covariance(np.radians(1.0), 0.005)
    for i, (_, rgb, camera, T_CO, _) in enumerate(as_sent(rendered_frames(object_path, frames, seed, scenes=2), 90, "444")):
        estimator.estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=camera, image=rgb))
        rect = crop_rect(camera, corners, T_CO, prior_cov)
        if rect is not None:  # the crop a tracking device sends (client_sdk.crop)
            x, y, w, h = rect
            cam = replace(camera, cx=camera.cx - x, cy=camera.cy - y, width=w, height=h)
            estimator.estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=cam, image=rgb[y:y + h, x:x + w]))
    return seen


def head_nodes(model) -> list[str]:
    """The last Conv and every node after it: the output head stays float. Its output holds the mask
    logit and the vector channels in one tensor, and one int8 scale over both (the logit's range is
    many times the vectors') left the keypoint directions a few degrees coarse."""
    nodes = list(model.graph.node)
    last = max(i for i, n in enumerate(nodes) if n.op_type == "Conv")
    tail, names = set(nodes[last].output), [nodes[last].name]
    for n in nodes[last + 1:]:
        if tail & set(n.input):
            tail |= set(n.output)
            names.append(n.name)
    return names


def quantize(model: Path, out: Path, inputs: list[np.ndarray], provenance: dict | None = None) -> Path:
    """Writes the static int8 (QDQ) model of `model` calibrated on `inputs`, its metadata carried over."""
    import onnx
    from onnxruntime.quantization import CalibrationDataReader, QuantFormat, QuantType, quantize_static
    from onnxruntime.quantization.shape_inference import quant_pre_process

    class Reader(CalibrationDataReader):
        def __init__(self):
            self._it = iter([{"image": np.ascontiguousarray(x)} for x in inputs])

        def get_next(self):
            return next(self._it, None)

    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(model), str(pre), skip_symbolic_shape=True)
        quantize_static(str(pre), str(out), Reader(), quant_format=QuantFormat.QDQ, per_channel=True,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        nodes_to_exclude=head_nodes(onnx.load(str(pre))))
    source = onnx.load(str(model))
    q = onnx.load(str(out))
    meta = {p.key: p.value for p in source.metadata_props}
    meta.update({"quantized": "int8 static QDQ, per-channel weights, min-max activations",
                 "quantized_from_sha256": hashlib.sha256(model.read_bytes()).hexdigest()[:16],
                 "calibration": json.dumps(provenance or {})})
    del q.metadata_props[:]
    for key, value in meta.items():
        q.metadata_props.add(key=key, value=value)
    onnx.save(q, str(out))
    return out


def run(args) -> int:
    from flextrack import assets

    if not args.model.is_file():
        raise FileNotFoundError(f"model {args.model} not found")
    object_path = assets.object_model(args.object)
    out = args.out or args.model.with_name(f"{args.model.stem}_int8.onnx")
    inputs = calibration_inputs(args.model, object_path, args.frames, args.seed)
    quantize(args.model, out, inputs, {"frames": args.frames, "seed": args.seed, "inputs": len(inputs),
                                            "object": object_path.name})
    print(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB), int8 static, calibrated on {len(inputs)} "
          f"network inputs of {args.frames} rendered frames (seed {args.seed})")
    return 0
