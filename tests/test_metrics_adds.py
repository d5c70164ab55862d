"""ADD-S (BOP's `adi`) against the BOP toolkit's definition: pose_error.adi transforms the model points by both
poses, builds a KD-tree of the estimated ones and averages each true point's distance to its nearest neighbour."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from flextrack.geometry import metrics, se3, so3


def bop_adi(T_est, T_gt, points):
    """bop_toolkit_lib.pose_error.adi, written out (R, t from the 4x4 poses)."""
    pts_est = points @ T_est[:3, :3].T + T_est[:3, 3]
    pts_gt = points @ T_gt[:3, :3].T + T_gt[:3, 3]
    nn_dists, _ = cKDTree(pts_est).query(pts_gt, k=1)
    return nn_dists.mean()


def random_pose(rng, angle=np.pi, dist=0.05):
    return se3.make(so3.exp(rng.normal(size=3) * angle / np.sqrt(3)), rng.normal(size=3) * dist + [0, 0, 1.2])


@pytest.mark.parametrize("seed", range(5))
def test_adds_equals_the_bop_definition(seed):
    rng = np.random.default_rng(seed)
    points = rng.normal(size=(800, 3)) * [0.05, 0.03, 0.02]
    T_gt = random_pose(rng)
    for angle, dist in ((0.01, 0.001), (0.2, 0.01), (np.pi, 0.05)):
        T_est = T_gt @ random_pose(rng, angle, dist) @ se3.make(np.eye(3), [0, 0, -1.2])
        expected = bop_adi(T_est, T_gt, points)
        assert metrics.adds_m(T_est, T_gt, points) == pytest.approx(expected, rel=1e-12, abs=1e-15)
        # one tree for many poses gives the same; ADD-S never exceeds ADD (each point's own partner is a candidate)
        assert metrics.AddS(points)(T_est, T_gt) == pytest.approx(expected, rel=1e-12)
        assert metrics.adds_m(T_est, T_gt, points) <= metrics.add_m(T_est, T_gt, points) + 1e-15


def test_adds_is_zero_for_a_symmetric_object_turned_by_its_symmetry():
    # a box's corners and face centres: symmetric under a half turn about each axis
    corners = np.array([[x, y, z] for x in (-0.04, 0.04) for y in (-0.03, 0.03) for z in (-0.02, 0.02)])
    points = np.vstack([corners, np.diag([0.04, 0.03, 0.02]), -np.diag([0.04, 0.03, 0.02])])
    T_gt = se3.make(so3.exp(np.array([0.3, -0.2, 0.1])), np.array([0.01, -0.02, 1.1]))
    T_est = T_gt @ se3.make(so3.exp(np.array([0.0, 0.0, np.pi])), np.zeros(3))  # the half turn about z
    assert metrics.add_m(T_est, T_gt, points) > 0.03  # ADD sees a wrong pose
    assert metrics.adds_m(T_est, T_gt, points) == pytest.approx(0.0, abs=1e-12)  # ADD-S sees the same shape
    assert metrics.adds_m(T_gt, T_gt, points) == pytest.approx(0.0, abs=1e-15)


def test_adds_on_a_full_mesh_is_fast_enough_to_report_for_every_answer():
    """A 20k-point mesh (the cat's full mesh has ~16k vertices): the brute force took 4.7 s a pair; the tree
    answers each pair without forming the 20k x 20k distances. Figures: `flextrack bench`-style prints belong in
    benchmarks, so this checks the result only, against the BOP definition."""
    rng = np.random.default_rng(7)
    points = rng.normal(size=(20_000, 3)) * [0.05, 0.03, 0.02]
    scorer = metrics.AddS(points)
    T_gt = random_pose(rng)
    T_est = T_gt @ random_pose(rng, 0.05, 0.002) @ se3.make(np.eye(3), [0, 0, -1.2])
    assert scorer(T_est, T_gt) == pytest.approx(bop_adi(T_est, T_gt, points), rel=1e-12)
