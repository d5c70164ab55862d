"""The default object is reproducible and asymmetric; rendered masks agree with the projected model."""

import hashlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial import cKDTree

from flextrack import assets
from flextrack.formats import bop
from flextrack.geometry import se3, so3
from flextrack.geometry.camera import PinholeCamera, project_model
from flextrack.simulator import default_object
from flextrack.simulator.render import Renderer, load_model
from flextrack.simulator.scene import make_scene

CAT = Path(__file__).resolve().parents[2] / "shared" / "data" / "lmo" / "models" / "obj_000006.ply"
DEFAULT_PLY = assets.default_object_model()  # generated on first use


def reference_mask(camera: PinholeCamera, T_CO: np.ndarray, mesh, supersample: int = 8) -> np.ndarray:
    """The model's silhouette: every projected triangle filled on a finer grid, sampled at pixel centres."""
    s = supersample
    uv = project_model(camera, T_CO, np.asarray(mesh.vertices))
    triangles = np.round(uv[mesh.faces] * s * 16).astype(np.int32)
    fine = np.zeros((camera.height * s, camera.width * s), np.uint8)
    for tri in triangles:
        cv2.fillConvexPoly(fine, tri, 1, lineType=cv2.LINE_8, shift=4)
    return fine[::s, ::s].astype(bool)


def centroid(mask: np.ndarray) -> np.ndarray:
    ys, xs = np.nonzero(mask)
    return np.array([xs.mean(), ys.mean()])


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_default_object_is_the_one_the_shipped_network_was_trained_on(tmp_path):
    ply = default_object.write(tmp_path)
    assert hashlib.sha256(ply.read_bytes()).hexdigest() == default_object.PLY_SHA256, \
        "the generator changed the object: retrain the shipped model, or restore the object"
    assert ply.read_bytes() == DEFAULT_PLY.read_bytes()
    assert (tmp_path / "models_info.json").read_text() == (DEFAULT_PLY.parent / "models_info.json").read_text()


def test_the_default_object_is_generated_on_first_use_whole_and_once(tmp_path, monkeypatch):
    home = tmp_path / "objects" / "default" / "models"
    monkeypatch.setattr(assets, "default_object_home", lambda: home)
    path = assets.resolve("objects/default/models/obj_000001.ply", tmp_path)  # a config's path into its folder
    assert path == home / "obj_000001.ply"
    assert hashlib.sha256(path.read_bytes()).hexdigest() == default_object.PLY_SHA256
    assert (home / "models_info.json").is_file()
    assert [p.name for p in home.parent.iterdir()] == ["models"]  # the staging folder is gone
    written = path.stat().st_mtime_ns
    assert assets.default_object_model() == path and path.stat().st_mtime_ns == written  # not generated again


def test_default_object_size_colours_and_no_symmetry():
    info = bop.read_models_info(DEFAULT_PLY.parent / "models_info.json")[default_object.BOP_OBJ_ID]
    assert abs(info["diameter"] - 150.0) < 0.5
    assert DEFAULT_PLY.stat().st_size < 1_000_000
    mesh = load_model(DEFAULT_PLY)
    colours = mesh.visual.vertex_colors[:, :3]
    assert len(np.unique(colours, axis=0)) > 500  # textured, not flat colours
    points = np.asarray(mesh.vertices)
    tree = cKDTree(points)
    # No proper rotation maps the surface onto itself: try the half and quarter turns about each axis
    # (and about the principal axes), where a symmetric shape would map onto itself.
    _, _, axes = np.linalg.svd(points - points.mean(axis=0))
    for axis in [*np.eye(3), *axes]:
        for angle in (np.pi / 2, np.pi, 3 * np.pi / 2):
            R = so3.exp(axis * angle)
            moved = (points - points.mean(axis=0)) @ R.T + points.mean(axis=0)
            gap_mm = 1000 * np.mean(tree.query(moved)[0])
            assert gap_mm > 5.0, f"near-symmetric under {np.degrees(angle):.0f} deg about {axis}"


POSES = [([2.0, 0.5, 0.3], [0.05, -0.03, 0.7]), ([0.0, 0.0, 0.0], [0.0, 0.0, 1.2]), ([1.0, 2.0, 0.3], [-0.2, 0.1, 1.0])]


@pytest.mark.parametrize("model", ["default", "cat"])
def test_object_only_mask_matches_projected_model(model):
    path = DEFAULT_PLY if model == "default" else CAT
    if not path.exists():
        pytest.skip(f"{path} absent (shared data not mounted)")
    with Renderer(PinholeCamera.linemod(), path) as renderer:
        for rotvec, t in POSES:
            T_CO = se3.make(so3.exp(np.array(rotvec)), np.array(t))
            frame = renderer.render(T_CO)
            assert frame.rgb.shape == (480, 640, 3) and frame.rgb.dtype == np.uint8
            assert frame.depth.dtype == np.float32
            ref = reference_mask(renderer.camera, T_CO, renderer.mesh)
            assert iou(frame.mask, ref) >= 0.98
            assert np.linalg.norm(centroid(frame.mask) - centroid(ref)) < 1.0
            assert not frame.rgb[~frame.mask].any() or frame.rgb[~frame.mask].mean() < 2  # black background
            z = se3.transform_points(T_CO, np.asarray(renderer.mesh.vertices))[:, 2]
            hit = frame.depth[frame.mask]
            assert z.min() - 1e-3 <= np.median(hit) <= z.max() + 1e-3


def test_scene_mode_lighting_varies_and_mask_matches():
    T_WO = se3.make(so3.exp(np.array([0, 0, 0.4])), np.array([0, 0, 0.043]))
    eye, target = np.array([-1.0, -0.5, 0.5]), np.array([0.0, 0.0, 0.04])
    z = (target - eye) / np.linalg.norm(target - eye)
    x = np.cross(z, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    T_WC = se3.make(np.stack([x, np.cross(z, x), z], axis=1), eye)
    T_CO = se3.inverse(T_WC) @ T_WO
    frames = []
    for seed in (0, 1):
        with Renderer(PinholeCamera.linemod(), DEFAULT_PLY, scene=make_scene(seed), T_WO=T_WO) as renderer:
            frames.append(renderer.render(T_CO))
            ref = reference_mask(renderer.camera, T_CO, renderer.mesh)
        assert iou(frames[-1].mask, ref) >= 0.98
        assert np.linalg.norm(centroid(frames[-1].mask) - centroid(ref)) < 1.0
        assert (frames[-1].depth > 0).all()  # the room closes the view: something everywhere
    background = ~frames[0].mask
    assert np.abs(frames[0].rgb[background].astype(int) - frames[1].rgb[background]).mean() > 10


def test_bad_inputs_are_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError):
        Renderer(model_path=tmp_path / "missing.ply")
    with pytest.raises(ValueError):
        Renderer(scene=make_scene(0))
    with Renderer() as renderer, pytest.raises(ValueError):
        renderer.render(np.full((4, 4), np.nan))
