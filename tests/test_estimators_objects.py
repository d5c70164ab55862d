"""Object registry: models in mm read into metres, sampled keypoints, diameter, config errors."""

import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from estimators.base import UnknownObject
from estimators.objects import ObjectRegistry, farthest_point_sample, load_object, load_object_folder
from flextrack import assets

LMO_CAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmo" / "models" / "obj_000006.ply"
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


@pytest.mark.parametrize("path", [LMO_CAT, DEFAULT_MODEL], ids=["lmo", "default"])
def test_bop_models_take_their_diameter_from_models_info(path):
    if not path.exists():
        pytest.skip(f"{path} is absent")
    model = load_object("obj", path)
    info = json.loads((path.parent / "models_info.json").read_text())[str(int(path.stem.split("_")[1]))]
    assert model.diameter_m == pytest.approx(info["diameter"] / 1000.0)
    assert 0.01 < np.ptp(model.vertices, axis=0).max() < 0.5  # metres, not millimetres


def _bop_folder(tmp_path, info: dict) -> Path:
    folder = tmp_path / "models"
    folder.mkdir()
    trimesh.creation.cylinder(radius=30.0, height=80.0, sections=64).export(folder / "obj_000003.ply")  # mm
    (folder / "models_info.json").write_text(json.dumps({"3": info}))
    return folder


def test_a_bop_folder_is_read_under_file_stems_with_its_symmetries_in_metres(tmp_path):
    # a cylinder about z, and a discrete flip about x (translated by 2 mm: the model sits off its axis)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])
    flip[:3, 3] = [0.0, 0.0, 2.0]
    folder = _bop_folder(tmp_path, {"diameter": 100.0, "symmetries_continuous": [{"axis": [0, 0, 1], "offset": [0, 0, 0]}],
                                    "symmetries_discrete": [flip.ravel().tolist()]})
    (model,) = load_object_folder(folder)
    assert model.object_id == "obj_000003" and model.diameter_m == pytest.approx(0.1)
    S = model.symmetries
    steps = int(np.ceil(np.pi / 0.01))  # bop_toolkit's discretisation of a continuous symmetry
    assert S.shape == (2 * steps, 4, 4) and np.allclose(S[0], np.eye(4))
    assert np.allclose(S[steps][:3, 3], [0.0, 0.0, 0.002])  # mm -> m
    for T in S[:: steps // 7]:  # every one a rotation that maps the rim (a circle about z) onto itself
        assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3), atol=1e-9)
        rim = np.array([[0.03, 0.0, 0.0], [0.0, 0.03, 0.0]]) @ T[:3, :3].T + T[:3, 3]
        assert np.allclose(np.hypot(rim[:, 0], rim[:, 1]), 0.03)
    plain = load_object("box", tmp_path / "models" / "obj_000003.ply", keypoint_count=4)
    assert plain.symmetries.shape == (2 * steps, 4, 4)  # load_object reads models_info.json beside the model too


def test_lmo_symmetric_objects_carry_their_symmetry():
    folder = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmo" / "models"
    if not folder.is_dir():
        pytest.skip(f"the shared data folder lacks LM-O models ({folder})")
    models = {m.object_id: m for m in load_object_folder(folder)}
    assert [i for i, m in models.items() if len(m.symmetries) > 1] == ["obj_000010", "obj_000011"]  # eggbox, glue
    glue = models["obj_000011"]
    moved = glue.vertices @ glue.symmetries[1][:3, :3].T + glue.symmetries[1][:3, 3]
    from scipy.spatial import cKDTree

    assert np.median(cKDTree(glue.vertices).query(moved)[0]) < 0.003  # the flip maps the glue onto itself


@pytest.mark.parametrize("make, why", [
    (lambda f: (f / "models_info.json").unlink(), "no models_info.json"),
    (lambda f: (f / "obj_000003.ply").unlink(), "no BOP models"),
    (lambda f: (f / "obj_000003.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nend_header\n\x00"),
     "does not load as a mesh"),
    (lambda f: (f / "models_info.json").write_text('{"4": {"diameter": 1.0}}'), "not listed"),
    (lambda f: trimesh.PointCloud(np.random.default_rng(0).normal(size=(50, 3))).export(f / "obj_000003.ply"),
     "no faces"),
])
def test_a_bad_bop_folder_says_what_is_wrong(tmp_path, make, why):
    folder = _bop_folder(tmp_path, {"diameter": 100.0})
    make(folder)
    with pytest.raises(ValueError, match=why):
        load_object_folder(folder)


def test_one_id_for_two_meshes_is_refused(box_ply, tmp_path):
    registry = ObjectRegistry([load_object("box", box_ply)])
    registry.add(load_object("box", box_ply))  # the same file again: no conflict
    other = tmp_path / "other.ply"
    other.write_bytes(box_ply.read_bytes())
    with pytest.raises(ValueError, match="registered twice"):
        registry.add(load_object("box", other))
