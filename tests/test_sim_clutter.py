"""Cluttered frames as a BOP folder: readable by the BOP readers and the prior evaluation, the object
where its ground truth says, occluded no more than the style allows."""

import json

import cv2
import numpy as np

from flextrack.evaluation.prior_eval import bop_frames
from flextrack.formats import bop
from flextrack.geometry.camera import PinholeCamera, project_model
from flextrack.simulator.clutter import ClutterStyle, write_bop_folder
from flextrack.simulator.render import load_model


def test_cluttered_frames_form_a_bop_folder(tmp_path):
    style = ClutterStyle(shapes=(10, 20), occluders=(1, 3), max_occlusion=0.4)
    out = write_bop_folder(tmp_path / "clutter", frames=3, seed=5, style=style)
    frames = bop_frames(out, 1)
    assert len(frames) == 3
    assert (out / "models" / "obj_000001.ply").is_file()
    assert 1 in bop.read_models_info(out / "models" / "models_info.json")
    info = json.loads((out / "test" / "000001" / "scene_gt_info.json").read_text())
    vertices = np.asarray(load_model(out / "models" / "obj_000001.ply").vertices)
    camera = PinholeCamera.linemod()
    for f in frames:
        assert info[str(f.frame_id)][0]["visib_fract"] >= 0.6 - 1e-9
        rgb = cv2.imread(str(f.rgb_path))
        assert rgb.shape == (480, 640, 3)
        uv = project_model(camera, f.T_gt, vertices)
        assert np.all(uv.min(axis=0) > -40) and np.all(uv.max(axis=0) < [680, 520])  # in view
        assert f.T_gt[2, 3] > 0.5
