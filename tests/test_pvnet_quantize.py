"""`flextrack train pvnet-quantize` (flextrack/training/quantize.py): the int8 copy keeps the float model's
metadata, says what it was made from, keeps the output head float, and answers close to the float model."""

import json

import numpy as np
import pytest

onnx = pytest.importorskip("onnx")
ort = pytest.importorskip("onnxruntime")

from flextrack import assets
from flextrack.training.quantize import head_nodes, quantize


def _run(path, x):
    return ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"image": x})[0]


def test_int8_copy_keeps_the_metadata_and_a_float_head_and_answers_close(tmp_path):
    model = assets.pvnet_model_path()
    rng = np.random.default_rng(0)
    inputs = [rng.random((1, 3, 64, 96), dtype=np.float32) for _ in range(3)]
    out = quantize(model, tmp_path / "q.onnx", inputs, {"frames": 0, "seed": 0})
    source = {p.key: p.value for p in onnx.load(str(model)).metadata_props}
    q = onnx.load(str(out))
    meta = {p.key: p.value for p in q.metadata_props}
    assert {k: meta[k] for k in source} == source  # keypoints, input scale, output stride carried over
    assert meta["quantized"].startswith("int8") and json.loads(meta["calibration"]) == {"frames": 0, "seed": 0}
    ops = {n.name: n.op_type for n in q.graph.node}
    assert "QuantizeLinear" in ops.values()
    head = head_nodes(onnx.load(str(model)))
    assert head[0] == "/head/Conv" and ops["/head/Conv"] == "Conv"
    producers = {o: n.op_type for n in q.graph.node for o in n.output}
    head_conv = next(n for n in q.graph.node if n.name == "/head/Conv")
    weights = {i.name: i for i in q.graph.initializer}
    assert head_conv.input[1] not in producers and weights[head_conv.input[1]].data_type == onnx.TensorProto.FLOAT
    ref, got = _run(model, inputs[0]), _run(out, inputs[0])
    assert got.shape == ref.shape
    vec_ref, vec_got = ref[0, 1:].reshape(-1, 2, *ref.shape[2:]), got[0, 1:].reshape(-1, 2, *ref.shape[2:])
    assert np.median(np.sum(vec_ref * vec_got, axis=1)) > 0.9  # unit vectors that mostly agree


def test_the_shipped_int8_copy_is_the_float_models(tmp_path):
    meta = {p.key: p.value for p in onnx.load(str(assets.pvnet_int8_model_path())).metadata_props}
    import hashlib

    assert meta["quantized_from_sha256"] == hashlib.sha256(assets.pvnet_model_path().read_bytes()).hexdigest()[:16]
