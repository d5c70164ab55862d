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


def bop_folder(root, shift_px, coloured=True, shaded=False):
    """One sphere (mm) at 0.5 m; the image is the colour field, the vertices carry the field's colour where the
    image shows them: at the truth's projection plus `shift_px`. `shaded`: the sphere's silhouette, moved by the
    same shift, drawn darker than the field around it (an outline for the edge measure)."""
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
    field = colour_field(uu, vv)
    if shaded:  # the projected sphere's outline (its vertices' convex hull) darkened inside, each pixel by the
        # share of it the hull covers (drawn 8 times finer: OpenCV's fill takes in every pixel the outline touches)
        fine = np.zeros((480 * 8, 640 * 8), np.uint8)
        cv2.fillConvexPoly(fine, cv2.convexHull(np.round((uv * 8 + 3.5) * 16).astype(np.int32)), 255, cv2.LINE_8, 4)
        cover = cv2.resize(fine, (640, 480), interpolation=cv2.INTER_AREA).astype(float) / 255.0
        field = field * (1.0 - 0.6 * cover[..., None])
    image = np.clip(field, 0, 255).astype(np.uint8)
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


def test_the_frames_edges_place_the_outline_against_the_truths(tmp_path):
    """The outline drawn 1 px right and 1.5 px up of the truth's: the edges along the truth's outline say so
    (within a fifth of a pixel: the drawn outline is the vertices' hull, the measured one the mesh's), and that
    it is no larger."""
    root = bop_folder(tmp_path / "bop", shift_px=np.array([1.0, -1.5]), shaded=True)
    out = tmp_path / "offset.json"
    assert gt_offset.run(args_for(root, out)) == 0
    edges = json.loads(out.read_text())["edges"]["pooled"]
    assert abs(edges["du_px"] - 1.0) < 0.2 and abs(edges["dv_px"] + 1.5) < 0.2
    assert abs(edges["wider_px"]) < 0.4 and abs(edges["taller_px"]) < 0.4
    assert all(edges["sides"][side]["instances"] == 1 for side in ("top", "bottom", "left", "right"))


def test_a_mesh_without_vertex_colours_is_a_clear_error(tmp_path, capsys):
    root = bop_folder(tmp_path / "bop", shift_px=np.zeros(2), coloured=False)
    assert gt_offset.run(args_for(root)) == 2
    assert "has no vertex colours" in capsys.readouterr().err


def test_an_unreadable_frame_is_a_clear_error(tmp_path, capsys):
    root = bop_folder(tmp_path / "bop", shift_px=np.zeros(2))
    (root / "test" / "000002" / "rgb" / "000000.png").write_bytes(b"not a png")
    assert gt_offset.run(args_for(root)) == 2
    assert "cannot read the image" in capsys.readouterr().err
