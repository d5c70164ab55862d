"""`flextrack evaluate gt-offset` finds a known shift between a BOP folder's ground truth and its image."""

import argparse
import json

import cv2
import numpy as np
import trimesh

from flextrack.evaluation import gt_offset

K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])


def colour_field(u, v):
    """A smooth, textured RGB field (px -> 0..255): each channel its own waves, so every shift reads differently."""
    return np.stack([128 + 100 * np.sin(u / 7.0) * np.cos(v / 9.0),
                     128 + 100 * np.sin(v / 6.0 + 1.0),
                     128 + 100 * np.cos((u + v) / 8.0)], axis=-1)


def bop_folder(root, shift_px, coloured=True):
    """One sphere (mm) at 0.5 m; the image is the colour field, the vertices carry the field's colour where the
    image shows them: at the truth's projection plus `shift_px`."""
    mesh = trimesh.creation.icosphere(subdivisions=4, radius=50.0)
    T = np.eye(4)
    T[:3, 3] = [0.01, -0.02, 0.5]
    P = mesh.vertices / 1000.0 @ T[:3, :3].T + T[:3, 3]
    uv = (P @ K.T)[:, :2] / P[:, 2:3] + shift_px
    if coloured:
        rgb = np.clip(colour_field(uv[:, 0], uv[:, 1]), 0, 255).astype(np.uint8)
        mesh.visual = trimesh.visual.ColorVisuals(mesh, vertex_colors=np.column_stack([rgb, np.full(len(rgb), 255)]))
    (root / "models").mkdir(parents=True)
    mesh.export(root / "models" / "obj_000001.ply")
    scene = root / "test" / "000002"
    (scene / "rgb").mkdir(parents=True)
    vv, uu = np.mgrid[0:480, 0:640].astype(float)
    image = np.clip(colour_field(uu, vv), 0, 255).astype(np.uint8)
    cv2.imwrite(str(scene / "rgb" / "000000.png"), cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    (scene / "scene_gt.json").write_text(json.dumps({"0": [{"obj_id": 1, "cam_R_m2c": T[:3, :3].ravel().tolist(),
                                                             "cam_t_m2c": (T[:3, 3] * 1000).tolist()}]}))
    (scene / "scene_camera.json").write_text(json.dumps({"0": {"cam_K": K.ravel().tolist(), "depth_scale": 1.0}}))
    (scene / "scene_gt_info.json").write_text(json.dumps({"0": [{"visib_fract": 1.0}]}))
    return root


def args_for(root, out=None):
    parser = argparse.ArgumentParser()
    gt_offset.add_arguments(parser)
    return parser.parse_args(["--bop", str(root), *(["--out", str(out)] if out else [])])


def test_the_shift_between_truth_and_image_is_found(tmp_path):
    root = bop_folder(tmp_path / "bop", shift_px=np.array([1.0, -1.5]))
    out = tmp_path / "offset.json"
    assert gt_offset.run(args_for(root, out)) == 0
    result = json.loads(out.read_text())
    assert result["instances"] == 1
    assert (result["pooled"]["du_px"], result["pooled"]["dv_px"]) == (1.0, -1.5)
    assert result["pooled"]["ncc_peak"] > 0.99 > result["pooled"]["ncc_at_truth"]
    assert result["options"]["min_visib"] == 0.8 and "date" in result  # the run's provenance


def test_a_mesh_without_vertex_colours_is_a_clear_error(tmp_path, capsys):
    root = bop_folder(tmp_path / "bop", shift_px=np.zeros(2), coloured=False)
    assert gt_offset.run(args_for(root)) == 2
    assert "has no vertex colours" in capsys.readouterr().err


def test_an_unreadable_frame_is_a_clear_error(tmp_path, capsys):
    root = bop_folder(tmp_path / "bop", shift_px=np.zeros(2))
    (root / "test" / "000002" / "rgb" / "000000.png").write_bytes(b"not a png")
    assert gt_offset.run(args_for(root)) == 2
    assert "cannot read the image" in capsys.readouterr().err
