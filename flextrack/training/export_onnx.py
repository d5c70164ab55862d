"""Export a trained PvnetNet to ONNX (fixed opset, dynamic batch and image size) and check it.

The ONNX file carries what the estimator needs to use it correctly as metadata: the keypoints in
the object frame (so the server can refuse a model trained with other keypoints), the frame ->
input scale and the output stride.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from flextrack.training.pvnet_data import INPUT_SCALE
from flextrack.training.pvnet_model import OUTPUT_STRIDE, PvnetNet

OPSET = 17


def export(net: PvnetNet, path: str | Path, keypoints_O: np.ndarray, metadata: dict | None = None) -> Path:
    """Writes the network as ONNX with metadata; returns the path."""
    import onnx

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    net = net.eval()
    dummy = torch.zeros(1, 3, 64, 64)
    torch.onnx.export(net, (dummy,), str(path), input_names=["image"], output_names=["out"], opset_version=OPSET,
                      dynamic_axes={"image": {0: "batch", 2: "height", 3: "width"},
                                    "out": {0: "batch", 2: "out_height", 3: "out_width"}},
                      dynamo=False)
    model = onnx.load(str(path))
    meta = {"keypoints_O": json.dumps(np.asarray(keypoints_O, dtype=float).tolist()),
            "input_scale": str(INPUT_SCALE), "output_stride": str(OUTPUT_STRIDE),
            "num_keypoints": str(len(keypoints_O))}
    meta.update({k: str(v) for k, v in (metadata or {}).items()})
    for key, value in meta.items():
        model.metadata_props.add(key=key, value=value)
    onnx.checker.check_model(model)
    onnx.save(model, str(path))
    return path


def max_difference(net: PvnetNet, path: str | Path, batch: int = 2, height: int = 96, width: int = 128,
                   seed: int = 0) -> float:
    """Largest absolute difference between torch and onnxruntime outputs on a random batch."""
    import onnxruntime as ort

    x = np.random.default_rng(seed).random((batch, 3, height, width), dtype=np.float32)
    with torch.no_grad():
        ref = net.eval()(torch.from_numpy(x)).numpy()
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = sess.run(None, {"image": x})[0]
    return float(np.max(np.abs(ref - got)))


def load_checkpoint_net(ckpt_path: str | Path) -> tuple[PvnetNet, dict]:
    ck = torch.load(ckpt_path, weights_only=False, map_location="cpu")
    net = PvnetNet(len(ck["keypoints_O"]), ck["config"]["width"])
    net.load_state_dict(ck["model"])
    return net.eval(), ck


def export_checkpoint(ckpt_path: str | Path, onnx_path: str | Path, metadata: dict | None = None) -> float:
    """Exports a training checkpoint; returns the torch/onnxruntime max difference."""
    net, ck = load_checkpoint_net(ckpt_path)
    meta = {"object_model": Path(ck["object_model"]).name, "diameter_m": ck["diameter_m"],
            "train_steps": ck["state"]["step"], "train_seed": ck["config"]["seed"]}
    meta.update(metadata or {})
    export(net, onnx_path, ck["keypoints_O"], meta)
    return max_difference(net, onnx_path)
