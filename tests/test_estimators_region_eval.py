"""`flextrack evaluate prior`: priors drawn in the wire convention, BOP folders read, answers scored,
and the JSON it writes (options, seeds, commit, host, date; why an estimator cannot run)."""

import json

import cv2
import numpy as np
import trimesh

from estimators.base import EstimateOutput, Estimator, InvalidInput, Status
from flextrack.cli import main as flextrack_main
from flextrack.evaluation.prior_eval import PriorLevel, Target, bop_frames, evaluate, parse_levels, perturb
from flextrack.formats import bop
from flextrack.geometry import se3, so3
from flextrack.wire import pose_error

T_TRUE = se3.make(so3.exp(np.array([0.3, -0.2, 0.1])), np.array([0.02, -0.01, 0.8]))


def test_levels_parse_and_priors_follow_the_wire_convention():
    levels = parse_levels("10:5, 20:10,none")
    assert [lv.label for lv in levels] == ["10mm/5deg", "20mm/10deg", "none"]
    rng = np.random.default_rng(0)
    errors = np.array([pose_error(perturb(T_TRUE, levels[0], rng), T_TRUE) for _ in range(4000)])
    # e = (d_theta, d_t) of the prior against the truth: zero mean, the level's sigmas per axis
    np.testing.assert_allclose(errors.mean(axis=0), 0, atol=0.003)
    np.testing.assert_allclose(errors.std(axis=0), [np.radians(5)] * 3 + [0.01] * 3, rtol=0.05)
    np.testing.assert_allclose(levels[0].covariance, np.diag([np.radians(5) ** 2] * 3 + [1e-4] * 3))


def bop_folder(root, frames=3):
    """A tiny BOP folder: a box (obj 7), grey frames, ground truth."""
    (root / "models").mkdir(parents=True)
    trimesh.creation.box(extents=(80.0, 60.0, 40.0)).export(root / "models" / "obj_000007.ply")
    scene = root / "test" / "000003"
    (scene / "rgb").mkdir(parents=True)
    K = np.array([[572.4, 0, 325.3], [0, 573.6, 242.0], [0, 0, 1.0]])
    for i in range(frames):
        cv2.imwrite(str(scene / "rgb" / f"{i:06d}.png"), np.full((480, 640, 3), 90, np.uint8))
    bop.write_scene_gt(scene / "scene_gt.json", dict.fromkeys(range(frames), T_TRUE), obj_id=7)
    bop.write_scene_camera(scene / "scene_camera.json", dict.fromkeys(range(frames), K))
    return root


class HalfWay(Estimator):
    """Moves the prior half way to the truth it was told; refuses without a prior."""

    kind = "halfway"

    def __init__(self):
        super().__init__("halfway", ["box"])

    def estimate(self, inp):
        if inp.prior_T_CO is None:
            raise InvalidInput("needs a prior")
        e = pose_error(inp.prior_T_CO, T_TRUE)
        T = se3.make(so3.exp(e[:3] / 2) @ inp.prior_T_CO[:3, :3], inp.prior_T_CO[:3, 3] + e[3:] / 2)
        return EstimateOutput(Status.OK, T, 1.0, inp.prior_covariance / 4)


def test_evaluate_scores_each_level(tmp_path):
    frames = bop_frames(bop_folder(tmp_path / "bop"), 7)
    assert [(f.scene, f.frame_id) for f in frames] == [(3, 0), (3, 1), (3, 2)]
    vertices = np.array(trimesh.creation.box(extents=(0.08, 0.06, 0.04)).vertices)
    targets = {7: Target("box", HalfWay(), vertices, 0.11, np.eye(4)[None])}
    out = evaluate(targets, frames, parse_levels("10:5,none"), 4, 0, 640, 480)
    a, none = out["10mm/5deg"]["summary"], out["none"]["summary"]
    assert a["answers"] == 12 and a["ok"] == 12
    assert a["median_proj_px"] < a["prior_median_proj_px"]  # half way: a better answer than the prior
    assert 1.0 < a["nees_mean"] < 20.0  # e ~ N(0, cov / 4): NEES ~ chi2(6)
    assert none["ok"] == 0 and none["share_proj_5px"] == 0.0 and none["median_proj_px"] is None
    assert {r["status"] for r in out["none"]["answers"]} == {"REFUSED"}
    assert all(np.all(np.isfinite(r["centre_offset_px"])) and len(r["centre_offset_px"]) == 2
               for r in out["10mm/5deg"]["answers"])  # where each answer puts the centre in the image
    assert not any("centre_offset_px" in r for r in out["none"]["answers"])
    again = evaluate(targets, frames, parse_levels("10:5"), 4, 0, 640, 480)
    assert again["10mm/5deg"]["summary"]["median_proj_px"] == a["median_proj_px"]  # seeded


def test_the_command_writes_why_an_estimator_cannot_run(tmp_path, capsys):
    root = bop_folder(tmp_path / "bop", frames=1)
    out = tmp_path / "result.json"
    rc = flextrack_main(["evaluate", "prior", "--bop", str(root), "--obj-id", "7", "--estimator", "pvnet",
                         "--draws", "1", "--out", str(out)])
    assert rc == 1 and "pvnet cannot run on obj_000007" in capsys.readouterr().out
    doc = json.loads(out.read_text())
    assert "trained for other keypoints" in doc["error"]
    assert len(doc["commit"]) == 40 and isinstance(doc["dirty"], bool) and doc["host"] and doc["date"]
    assert doc["options"]["draws"] == 1 and doc["seeds"]["seed"] == 0 and doc["frames"] == 1


def test_the_colours_at_truth_oracle_is_refused_for_an_estimator_that_is_not_region(tmp_path, capsys):
    root = bop_folder(tmp_path / "bop", frames=1)
    rc = flextrack_main(["evaluate", "prior", "--bop", str(root), "--obj-id", "7", "--estimator", "pnp",
                         "--draws", "1", "--colours-at-truth"])
    assert rc == 1 and "--colours-at-truth is an oracle for a 'region' estimator" in capsys.readouterr().out


def test_symmetric_objects_score_against_the_nearest_symmetric_pose(tmp_path):
    """An answer that is the truth turned by one of the object's symmetries scores 0 px; without the symmetry it
    is far off. The flipped prior is the same place in the image, upside down."""
    frames = bop_frames(bop_folder(tmp_path / "bop", frames=1), 7)
    vertices = np.array(trimesh.creation.box(extents=(0.08, 0.06, 0.04)).vertices)
    half_turn = se3.make(so3.exp(np.array([0.0, 0.0, np.pi])), np.zeros(3))

    class Turned(HalfWay):
        def estimate(self, inp):
            return EstimateOutput(Status.OK, T_TRUE @ half_turn, 1.0, np.eye(6) * 1e-4)

    symmetric = {7: Target("box", Turned(), vertices, 0.11, np.stack([np.eye(4), half_turn]))}
    plain = {7: Target("box", Turned(), vertices, 0.11, np.eye(4)[None])}
    s_sym = evaluate(symmetric, frames, parse_levels("10:5"), 1, 0, 640, 480)["10mm/5deg"]
    s_plain = evaluate(plain, frames, parse_levels("10:5"), 1, 0, 640, 480)["10mm/5deg"]
    assert s_sym["summary"]["median_proj_px"] < 1e-6 and s_sym["summary"]["share_add_10"] == 1.0
    assert s_plain["summary"]["median_proj_px"] > 20 and s_plain["summary"]["share_ok_wrong"] == 1.0
    assert set(s_sym["by_object"]) == {"7"} and set(s_sym["by_visib"]) == {"unknown"}
    flip = se3.turned_about_line_of_sight(T_TRUE, np.zeros(3))
    c = T_TRUE[:3, 3]
    np.testing.assert_allclose(flip[:3, 3], c, atol=1e-12)  # the centre stays where it was
    axis = so3.log(flip[:3, :3] @ T_TRUE[:3, :3].T)
    np.testing.assert_allclose(np.abs(axis), np.pi * np.abs(c) / np.linalg.norm(c), atol=1e-9)


def test_prior_levels_label_none():
    assert PriorLevel(None, None).label == "none" and PriorLevel(None, None).seed_key == (0, 0)
