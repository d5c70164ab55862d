"""gt_oracle: exact ground truth, interpolation, not-in-view cases, seeded noise of the stated size."""

import numpy as np
import pytest

from estimators.base import EstimateInput, Status, UnknownObject, UnknownSequence
from estimators.gt_oracle import GtOracleEstimator
from estimators.registry import EstimatorRegistry
from flextrack import wire
from flextrack.formats import sequence as sequence_io
from flextrack.geometry import se3, so3
from flextrack.geometry.camera import PinholeCamera
from flextrack.testing.toy_sequence import write_orbit_sequence
from flextrack.v1 import pose_estimation_pb2 as pb
from service.estimation import EstimationService


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return write_orbit_sequence(tmp_path_factory.mktemp("seqs") / "orbit", frames=20, missing=(10,))


def ask(oracle, t_ns, **kw):
    return oracle.estimate(EstimateInput(frame_id=0, capture_time_ns=int(t_ns), **kw))


def test_zero_noise_returns_the_ground_truth_exactly(seq):
    oracle = GtOracleEstimator(sequence_roots=[seq.root.parent])
    assert oracle.sequences == ["orbit"] and oracle.objects == ["toy"]
    gt = sequence_io.load(seq.root).gt_T_CO  # as stored in scene_gt.json (mm, so not bit-equal to seq.gt_T_CO)
    for frame_id, t_ns in zip(seq.frame_ids, seq.frame_times_ns):
        out = ask(oracle, t_ns, sequence="orbit", object_id="toy")
        if frame_id == 10:
            assert out.status is Status.OBJECT_NOT_FOUND
            continue
        assert out.status is Status.OK and np.array_equal(out.T_CO, gt[int(frame_id)])


def test_between_frames_it_interpolates_linearly_and_by_slerp(seq):
    oracle = GtOracleEstimator(sequence_roots=[seq.root])  # a folder with rig.yaml is one sequence
    t0, t1 = seq.frame_times_ns[3], seq.frame_times_ns[4]
    out = ask(oracle, t0 + (t1 - t0) // 4)
    expected = se3.interpolate(seq.gt_T_CO[3], seq.gt_T_CO[4], ((t1 - t0) // 4) / (t1 - t0))
    assert out.status is Status.OK and np.allclose(out.T_CO, expected, atol=1e-12)
    # a frame's own pose is exact (the floor only keeps the matrix invertible); an interpolated one is not
    at_frame = ask(oracle, t0).covariance
    assert np.sqrt(at_frame[3, 3]) < 1e-7
    assert np.sqrt(out.covariance[3, 3]) == pytest.approx(np.hypot(1e-8, 2e-6))


def test_not_in_view_is_object_not_found(seq):
    oracle = GtOracleEstimator(sequence_roots=[seq.root.parent])
    t = seq.frame_times_ns
    assert ask(oracle, t[0] - 1).status is Status.OBJECT_NOT_FOUND  # before the ground truth
    assert ask(oracle, t[-1] + 1).status is Status.OBJECT_NOT_FOUND  # after it
    assert ask(oracle, (t[9] + t[10]) // 2).status is Status.OBJECT_NOT_FOUND  # next to a frame without it
    narrow = PinholeCamera(600.0, 600.0, -500.0, 240.0, 640, 480)  # principal point far off: centre off-image
    out = ask(oracle, t[0], camera=narrow)
    assert out.status is Status.OBJECT_NOT_FOUND and "outside the image" in out.message


def test_unknown_sequence_and_object_raise(seq, tmp_path):
    oracle = GtOracleEstimator(sequence_roots=[seq.root.parent])
    with pytest.raises(UnknownSequence, match="'other'.*orbit"):
        ask(oracle, seq.frame_times_ns[0], sequence="other")
    with pytest.raises(UnknownObject, match="cup"):
        ask(oracle, seq.frame_times_ns[0], object_id="cup")
    second = write_orbit_sequence(tmp_path / "second", frames=5, object_id="duck")
    assert oracle.add_sequence(second.root) == "second"
    with pytest.raises(UnknownSequence, match="no sequence ''"):  # two loaded: a request must name one
        ask(oracle, seq.frame_times_ns[0])
    assert ask(oracle, seq.frame_times_ns[0], sequence="orbit", object_id="duck").status is Status.OBJECT_NOT_FOUND


def test_noise_has_the_configured_std_per_axis_over_2000_requests(seq):
    noise_t_m, noise_r_deg = 0.003, 0.3
    noisy = GtOracleEstimator("noisy", [seq.root.parent], noise_t_m=noise_t_m, noise_r_deg=noise_r_deg, seed=5)
    exact = GtOracleEstimator("exact", [seq.root.parent])
    service = EstimationService(EstimatorRegistry([noisy, exact]))
    # 2,000 distinct capture times (each draws its own noise) in frames 0..9, which all have ground truth
    times = np.linspace(seq.frame_times_ns[0], seq.frame_times_ns[9], 2000).astype(np.int64)
    dt, dr = [], []
    for k, t_ns in enumerate(times):
        p = service.estimate(pb.EstimateRequest(frame_id=k, capture_time_ns=int(t_ns), estimator="noisy")).pose
        T = wire.pose_from_pb(p)
        T_gt = ask(exact, t_ns).T_CO
        dt.append(T[:3, 3] - T_gt[:3, 3])
        dr.append(so3.log(T[:3, :3] @ T_gt[:3, :3].T))
    std_t, std_r = np.std(dt, axis=0), np.degrees(np.std(dr, axis=0))
    assert np.all(np.abs(std_t / noise_t_m - 1) < 0.1), std_t
    assert np.all(np.abs(std_r / noise_r_deg - 1) < 0.1), std_r
    assert np.all(np.abs(np.mean(dt, axis=0)) < 0.1 * noise_t_m)


def test_noise_is_a_pure_function_of_seed_sequence_object_and_time(seq):
    make = lambda seed: GtOracleEstimator("n", [seq.root.parent], noise_t_m=0.003, noise_r_deg=0.3, seed=seed)
    a, b = make(1), make(1)
    times = seq.frame_times_ns[:8]
    forward = [ask(a, t).T_CO for t in times]
    backward = [ask(b, t).T_CO for t in times[::-1]][::-1]
    assert all(np.array_equal(x, y) for x, y in zip(forward, backward))
    assert not np.array_equal(ask(make(2), times[0]).T_CO, forward[0])
