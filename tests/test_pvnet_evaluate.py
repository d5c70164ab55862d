"""`flextrack train pvnet-eval`: rendered frames (rolled ones too) through the estimator, scored and drawn."""

import json

import cv2
import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from flextrack import assets
from flextrack.formats import bop
from flextrack.geometry import se3, so3
from flextrack.training.evaluate import bop_frames, evaluate, rendered_frames

SHIPPED = assets.pvnet_model_path()


def test_a_rolled_camera_sees_the_same_viewpoints_turned():
    upright = list(rendered_frames(assets.default_object_model(), 2, seed=11, scenes=1))
    rolled = list(rendered_frames(assets.default_object_model(), 2, seed=11, scenes=1, roll_deg=90.0))
    turn = se3.make(so3.exp(np.array([0.0, 0.0, np.pi / 2])), np.zeros(3))
    for (_, rgb, _, T, _), (_, rgb_rolled, _, T_rolled, _) in zip(upright, rolled):
        assert np.allclose(T_rolled, turn @ T)
        assert rgb.shape == rgb_rolled.shape and not np.array_equal(rgb, rgb_rolled)


@pytest.mark.skipif(not SHIPPED.is_file(), reason=f"no shipped model at {SHIPPED}")
def test_evaluation_scores_every_frame_and_writes_its_results(tmp_path):
    frames = rendered_frames(assets.default_object_model(), 3, seed=20261122, scenes=1, roll_deg=180.0)
    summary = evaluate(SHIPPED, assets.default_object_model(), frames, tmp_path, sheet=3, rotations=4)
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["rotations"] == 4 and len(saved["frames"]) == 3
    assert saved["provenance"]["options"]["rotations"] == 4 and {"commit", "dirty", "host", "date"} <= set(saved["provenance"])
    assert summary["rendered"]["frames"] == 3 and 0.0 <= summary["rendered"]["proj_below_5px"] <= 1.0
    # ADD-S beside ADD on every frame (never above it); ADD(-S) is ADD for the default object (no symmetry)
    s = summary["rendered"]
    assert all(f["adds_mm"] <= f["add_mm"] + 1e-9 for f in saved["frames"])
    assert s["adds_below_10pct"] >= s["add_below_10pct"] and not s["symmetric"]
    assert s["add_s_below_10pct"] == s["add_below_10pct"]
    assert (tmp_path / "poses.jpg").stat().st_size > 0


def test_a_simulated_sequence_folder_is_scored_on_its_frames_with_an_image(tmp_path):
    """A sequence folder has BOP ground truth for every frame but images only of the frames sent, and no
    scene_gt_info.json: those frames, one group."""
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1.0]])
    poses = {f: se3.make(np.eye(3), [0.0, 0.0, 0.5 + 0.1 * f]) for f in range(3)}
    bop.write_scene_gt(tmp_path / "scene_gt.json", poses, obj_id=1)
    bop.write_scene_camera(tmp_path / "scene_camera.json", {f: K for f in poses})
    (tmp_path / "rgb").mkdir()
    for f in (0, 2):
        cv2.imwrite(str(tmp_path / "rgb" / f"{f:06d}.png"), np.zeros((48, 64, 3), np.uint8))
    frames = list(bop_frames(tmp_path, obj_id=1))
    assert [name for name, *_ in frames] == ["000000", "000002"] and {f[4] for f in frames} == {"all"}
    assert np.allclose(frames[1][3], poses[2]) and frames[1][2].width == 64


def test_frames_as_sent_keep_their_colour_resolution():
    """The device sends JPEG with full-resolution colour (4:4:4): JPEG's usual 4:2:0 blurs colour edges,
    which the pvnet refinement fits to. `--jpeg` scores frames through the same encoding."""
    import io

    from PIL import Image, JpegImagePlugin

    from flextrack.runners.payload import frame_jpeg
    from flextrack.training.evaluate import as_sent

    stripes = np.zeros((48, 64, 3), np.uint8)
    stripes[:, ::2] = (200, 40, 40)  # 1 px columns of red and black: all colour detail
    for chroma, sampling in (("444", 0), ("420", 2)):
        assert JpegImagePlugin.get_sampling(Image.open(io.BytesIO(frame_jpeg(stripes, 90, chroma)))) == sampling
    (_, sent_444, *_), = as_sent([("f", stripes, None, np.eye(4), "g")], 90, "444")
    (_, sent_420, *_), = as_sent([("f", stripes, None, np.eye(4), "g")], 90, "420")
    assert sent_444.shape == stripes.shape
    error = {name: np.abs(img.astype(int) - stripes).mean() for name, img in (("444", sent_444), ("420", sent_420))}
    assert error["444"] < 0.5 * error["420"], error
