"""`flextrack train pvnet-eval`: rendered frames (rolled ones too) through the estimator, scored and drawn."""

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("onnxruntime")

from flextrack.geometry import se3, so3
from training.cli import DEFAULT_OBJECT
from training.evaluate import evaluate, rendered_frames

SHIPPED = Path(__file__).resolve().parents[1] / "models" / "pvnet_default" / "pvnet.onnx"


def test_a_rolled_camera_sees_the_same_viewpoints_turned():
    upright = list(rendered_frames(DEFAULT_OBJECT, 2, seed=11, scenes=1))
    rolled = list(rendered_frames(DEFAULT_OBJECT, 2, seed=11, scenes=1, roll_deg=90.0))
    turn = se3.make(so3.exp(np.array([0.0, 0.0, np.pi / 2])), np.zeros(3))
    for (_, rgb, _, T, _), (_, rgb_rolled, _, T_rolled, _) in zip(upright, rolled):
        assert np.allclose(T_rolled, turn @ T)
        assert rgb.shape == rgb_rolled.shape and not np.array_equal(rgb, rgb_rolled)


@pytest.mark.skipif(not SHIPPED.is_file(), reason=f"no shipped model at {SHIPPED}")
def test_evaluation_scores_every_frame_and_writes_its_results(tmp_path):
    frames = rendered_frames(DEFAULT_OBJECT, 3, seed=20261122, scenes=1, roll_deg=180.0)
    summary = evaluate(SHIPPED, DEFAULT_OBJECT, frames, tmp_path, sheet=3, rotations=4)
    saved = json.loads((tmp_path / "results.json").read_text())
    assert saved["rotations"] == 4 and len(saved["frames"]) == 3
    assert summary["rendered"]["frames"] == 3 and 0.0 <= summary["rendered"]["proj_below_5px"] <= 1.0
    assert (tmp_path / "poses.jpg").stat().st_size > 0
