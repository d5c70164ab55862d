"""Training data and the `flextrack train pvnet` command (a tiny run: checkpoint, resume, plot, ONNX)."""

import json

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("pyrender")

from estimators.objects import load_object
from flextrack import assets
from flextrack.geometry import se3
from flextrack.geometry.camera import PinholeCamera
from flextrack.training.pvnet_data import PatchSampler, RenderedViews, full_to_input, render_views, targets


@pytest.fixture(scope="module")
def views():
    obj = load_object("default", assets.default_object_model())
    return obj, render_views(obj.model_path, obj.keypoints, obj.diameter_m, n=4, seed=1)


def test_rendered_crops_line_up_with_their_keypoints(views):
    """Projected model vertices land on the rendered object in the half-resolution crop."""
    obj, v = views
    camera = PinholeCamera.linemod()
    for rgba, kp, T_CO in zip(v.rgba, v.keypoints, v.poses):
        full_kp = full_to_input(camera.project(se3.transform_points(T_CO, obj.keypoints)))
        offset = full_kp[-1] - kp[-1]  # the crop's origin
        assert np.allclose(full_kp - offset, kp, atol=1e-3) and np.allclose(offset, np.round(offset))
        pts = full_to_input(camera.project(se3.transform_points(T_CO, obj.vertices[::50]))) - offset
        ij = np.round(pts).astype(int)
        inside = (ij >= 0).all(1) & (ij < rgba.shape[0]).all(1)
        assert inside.mean() > 0.99
        assert np.mean(rgba[ij[inside, 1], ij[inside, 0], 3] > 0) > 0.95


def test_patches_and_targets_are_consistent(views):
    _, v = views
    imgs, masks, kps = PatchSampler(v, size=64, seed=2).batch(6)
    assert imgs.shape == (6, 64, 64, 3) and imgs.dtype == np.uint8 and masks.shape == (6, 64, 64)
    m, vec = targets(masks, kps)
    assert m.shape == (6, 32, 32) and vec.shape == (6, 18, 32, 32)
    b, i, j = np.argwhere(m)[0]
    d = kps[b, :, :] - np.array([2 * j + 0.5, 2 * i + 0.5])
    assert np.allclose(vec[b].reshape(9, 2, 32, 32)[:, :, i, j], d / np.linalg.norm(d, axis=1, keepdims=True),
                       atol=1e-4)


def test_patches_turn_the_object_as_far_as_asked(views):
    """The in-plane turn of a patch (the keypoint layout about the centre) stays within +-turn_deg."""
    _, v = views
    one = RenderedViews(v.rgba[:1], v.keypoints[:1], v.poses[:1])
    heading = lambda kp: np.degrees(np.arctan2(*(kp[..., 0, ::-1] - kp[..., -1, ::-1]).T))
    turns = {}
    for turn_deg in (15.0, 180.0):
        _, _, kps = PatchSampler(one, size=64, seed=3, turn_deg=turn_deg).batch(200)
        turns[turn_deg] = np.abs((heading(kps) - heading(one.keypoints[0]) + 180) % 360 - 180)
    assert turns[15.0].max() < 15.01 and turns[180.0].max() > 150 and np.median(turns[180.0]) > 60


def test_train_command_checkpoints_resumes_and_exports(tmp_path):
    from flextrack.cli import main

    out = tmp_path / "run"
    common = ["train", "pvnet", "--object", "default", "--out", str(out), "--views", "6", "--batch", "2",
              "--size", "32", "--width", "4"]
    assert main(common + ["--steps", "2"]) == 0
    assert json.loads((out / "log.json").read_text())["step"] == 2
    assert main(common + ["--steps", "3", "--resume"]) == 0
    assert json.loads((out / "log.json").read_text())["step"] == 3
    for name in ("checkpoint.pt", "views.npz", "loss.png", "pvnet.onnx"):
        assert (out / name).stat().st_size > 0


def test_train_command_rejects_bad_input(tmp_path, capsys):
    from flextrack.cli import main

    assert main(["train", "pvnet", "--object", str(tmp_path / "nope.ply"), "--out", str(tmp_path)]) == 2
    assert "not found" in capsys.readouterr().err
    assert main(["train", "pvnet", "--out", str(tmp_path), "--size", "40"]) == 2
