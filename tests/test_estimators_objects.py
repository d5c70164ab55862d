"""Object registry: models in mm read into metres, sampled keypoints, diameter, config errors."""

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from estimators.base import UnknownObject
from estimators.objects import ObjectRegistry, farthest_point_sample, load_object
from flextrack import assets

LMO_CAT = Path("/work/shared/data/lmo_cat/models/obj_000006.ply")
DEFAULT_MODEL = assets.default_object_model()


@pytest.fixture
def box_ply(tmp_path) -> Path:
    path = tmp_path / "box.ply"
    trimesh.creation.box(extents=(100.0, 60.0, 20.0)).export(path)  # mm
    return path


def test_box_model_is_read_in_metres_with_sampled_keypoints_and_centre(box_ply):
    model = load_object("box", box_ply)
    assert np.allclose(np.abs(model.vertices).max(axis=0), [0.05, 0.03, 0.01])
    assert model.keypoints.shape == (9, 3)
    assert np.allclose(model.keypoints[-1], 0.0)  # the box centre comes last
    # 8 keypoints on a box's 8 vertices: farthest-point sampling picks every corner once
    assert {tuple(np.round(k, 6)) for k in model.keypoints[:8]} == {tuple(np.round(c, 6)) for c in model.bbox_corners}
    assert model.diameter_m == pytest.approx(np.linalg.norm([0.1, 0.06, 0.02]))


def test_farthest_point_sample_spreads_points():
    points = np.random.default_rng(0).normal(size=(500, 3))
    picked = farthest_point_sample(points, 6)
    nearest = min(np.linalg.norm(a - b) for i, a in enumerate(picked) for b in picked[i + 1:])
    assert nearest > 1.0  # a random pick of 6 of 500 normals would have some much closer pair


def test_given_keypoints_are_used_as_they_are(box_ply, tmp_path):
    given = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [0.0, 0.0, 0.01]])
    assert np.array_equal(load_object("box", box_ply, given).keypoints, given)
    np.savetxt(tmp_path / "kp.txt", given)
    assert np.allclose(load_object("box", box_ply, tmp_path / "kp.txt").keypoints, given)
    with pytest.raises(ValueError, match="keypoints"):
        load_object("box", box_ply, [[0.0, 1.0]])


def test_missing_model_and_unknown_object_say_what_is_wrong(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        load_object("x", tmp_path / "nope.ply")
    with pytest.raises(UnknownObject, match="ghost"):
        ObjectRegistry().get("ghost")


def test_registry_from_config_resolves_paths_and_rejects_unknown_keys(box_ply):
    registry = ObjectRegistry.from_config({"box": {"model": box_ply.name, "keypoint_count": 4}}, box_ply.parent)
    assert registry.ids() == ["box"] and registry.get("box").keypoints.shape == (5, 3)
    with pytest.raises(ValueError, match="modle"):
        ObjectRegistry.from_config({"box": {"modle": "box.ply"}}, box_ply.parent)


@pytest.mark.parametrize("path", [LMO_CAT, DEFAULT_MODEL], ids=["lmo_cat", "default"])
def test_bop_models_take_their_diameter_from_models_info(path):
    if not path.exists():
        pytest.skip(f"{path} is absent")
    model = load_object("obj", path)
    info = json.loads((path.parent / "models_info.json").read_text())[str(int(path.stem.split("_")[1]))]
    assert model.diameter_m == pytest.approx(info["diameter"] / 1000.0)
    assert 0.01 < np.ptp(model.vertices, axis=0).max() < 0.5  # metres, not millimetres
