"""The PVNet network: output shape and unit vectors, and the ONNX export agreeing with torch."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from flextrack.training.export_onnx import OPSET, export, max_difference
from flextrack.training.pvnet_model import PvnetNet


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    return PvnetNet(num_keypoints=9, width=8).eval()


@pytest.mark.parametrize("height,width", [(64, 64), (240, 320), (100, 130)])
def test_forward_shape_and_unit_vectors(net, height, width):
    with torch.no_grad():
        out = net(torch.rand(2, 3, height, width))
    assert out.shape == (2, 1 + 2 * 9, (height + 1) // 2, (width + 1) // 2)
    vec = out[:, 1:].reshape(2, 9, 2, *out.shape[-2:])
    norm = vec.norm(dim=2)
    assert norm.max() <= 1 + 1e-5 and norm.min() > 0.99


def test_onnx_export_agrees_with_torch_at_any_batch_and_size(net, tmp_path):
    import onnx

    keypoints = np.arange(27, dtype=float).reshape(9, 3) / 100
    path = export(net, tmp_path / "net.onnx", keypoints, {"note": "test"})
    model = onnx.load(str(path))
    assert model.opset_import[0].version == OPSET
    meta = {p.key: p.value for p in model.metadata_props}
    assert np.allclose(np.array(eval(meta["keypoints_O"])), keypoints)
    for batch, h, w in [(1, 64, 64), (3, 96, 128)]:
        assert max_difference(net, path, batch, h, w) < 1e-3
