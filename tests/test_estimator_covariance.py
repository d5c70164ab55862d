"""Every estimator sends a symmetric positive-definite 6x6 covariance with each pose, and it is
calibrated: the mean NEES of seeded synthetic answers lies in the chi2(6) mean's 95 % interval."""

import numpy as np
import pytest

from estimators.base import EstimateInput, Status
from estimators.gt_oracle import FLOOR_R_DEG, FLOOR_T_M, GtOracleEstimator
from flextrack import wire
from flextrack.evaluation import nees_calibration as nc
from flextrack.formats import sequence as sequence_io
from flextrack.testing.toy_sequence import write_orbit_sequence


def assert_spd(cov):
    assert cov is not None and cov.shape == (6, 6)
    assert np.allclose(cov, cov.T, rtol=0, atol=1e-12 * np.max(np.abs(cov)))
    assert np.all(np.linalg.eigvalsh(cov) > 0)
    wire.check_covariance(cov)  # what the service sends must pass what a receiver checks


def test_chi2_mean_interval_matches_the_stated_one():
    lo, hi = nc.mean_interval(200)
    assert lo == pytest.approx(5.529, abs=1e-3) and hi == pytest.approx(6.489, abs=1e-3)


# ---- gt_oracle --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def orbit(tmp_path_factory):
    return write_orbit_sequence(tmp_path_factory.mktemp("seqs") / "orbit", frames=300)


def test_gt_oracle_exact_answers_carry_the_floor(orbit):
    oracle = GtOracleEstimator(sequence_roots=[orbit.root])
    out = oracle.estimate(EstimateInput(frame_id=0, capture_time_ns=int(orbit.frame_times_ns[0])))
    assert out.status is Status.OK
    assert_spd(out.covariance)
    assert np.allclose(np.sqrt(np.diag(out.covariance)), [np.radians(FLOOR_R_DEG)] * 3 + [FLOOR_T_M] * 3)


def test_gt_oracle_noisy_answers_are_calibrated(orbit):
    oracle = GtOracleEstimator(sequence_roots=[orbit.root], noise_t_m=0.003, noise_r_deg=0.3, seed=5)
    truth = sequence_io.load(orbit.root).gt_T_CO
    values = []
    for frame_id, t_ns in zip(orbit.frame_ids, orbit.frame_times_ns):
        out = oracle.estimate(EstimateInput(frame_id=int(frame_id), capture_time_ns=int(t_ns)))
        assert out.status is Status.OK
        values.append(nc.nees(wire.pose_error(out.T_CO, truth[int(frame_id)]), out.covariance))
    assert_spd(out.covariance)
    s = nc.summarise(values)
    assert s["n"] == 300 and s["passed"], s


# ---- pnp --------------------------------------------------------------------------------------

def test_pnp_covariance_is_calibrated_on_noisy_keypoints():
    """1 px keypoint noise, a gross outlier in 30 % of the frames. PnP's covariance comes from the
    residuals of 9 keypoints (12 degrees of freedom), so its NEES is F-like, not chi2(6): mean 6,
    median lower, a longer tail; the mean of n answers scatters about 1.4 times as much as a chi2(6)
    mean would, and from seed to seed more (at 1 px: 6.22 from 1000 answers of seed 2, 5.62 from 2000 of seed 3), so the
    bound here is 6 +- 8 % (4.5 of those standard errors for 2000 answers): a calibration off by more fails."""
    rows = nc.pnp_answers(2000, seed=3, noise_px=1.0)  # not the inflation's tuning seed (1) nor the report's (2)
    assert len(rows) >= 1950
    s = nc.summarise(r["nees"] for r in rows)
    assert abs(s["mean"] - 6.0) < 4.5 * 1.4 * np.sqrt(12.0 / s["n"]), s
    assert 4.3 < s["median"] < 5.5 and 0.04 < s["share_above_q95"] < 0.12, s


def test_the_nees_command_stores_its_summaries_answers_and_provenance_and_the_report_renders_them(tmp_path):
    import csv
    import json

    from flextrack.cli import main as flextrack_main
    from flextrack.report import render_nees

    out = tmp_path / "nees"
    flextrack_main(["evaluate", "nees", "--estimators", "pnp", "--pnp-answers", "40", "--pnp-tune-answers", "40",
                    "--out", str(out)])
    data = json.loads((out / "nees.json").read_text())
    assert data["provenance"]["options"]["pnp_answers"] == 40 and data["provenance"]["wall_s"] > 0
    assert data["provenance"]["options"]["command"] == "flextrack evaluate nees"
    (entry,) = data["estimators"]
    with open(out / "answers.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == entry["heldout_all"]["n"] >= 38 and {r["estimator"] for r in rows} == {"pnp"}
    mean_nees = np.mean([float(r["nees"]) for r in rows])
    assert mean_nees == pytest.approx(entry["heldout_all"]["mean"], rel=1e-5)
    assert len(entry["heldout_below_max_2d"]["mean_error_deg_mm"]) == 6
    text = render_nees(out)
    assert "| pnp | all | " in text and "Source: `flextrack evaluate nees" in text


def test_pnp_exact_keypoints_keep_the_floor_and_noisier_ones_widen_it():
    from estimators.objects import ObjectRegistry
    from estimators.pnp import PnpEstimator
    from flextrack.geometry import se3, so3
    from flextrack.geometry.camera import PinholeCamera

    obj = nc._default_object()
    pnp = PnpEstimator(ObjectRegistry([obj]))
    camera = PinholeCamera.linemod()
    T = se3.make(so3.exp(np.array([2.0, 0.3, -0.2])), np.array([0.02, -0.01, 0.8]))
    uv = camera.project(se3.transform_points(T, obj.keypoints))
    traces = []
    for noise in (0.0, 0.5, 3.0):
        noisy = uv + np.random.default_rng(0).normal(0, noise, uv.shape)
        out = pnp.estimate(EstimateInput(0, 0, camera=camera, keypoints=np.column_stack([np.arange(len(uv)), noisy])))
        assert out.status is Status.OK
        assert_spd(out.covariance)
        traces.append(np.trace(out.covariance[3:, 3:]))
    assert traces[0] > 0 and traces[0] <= traces[1] < traces[2]
    # the exact fit claims the floor's 0.3 px: its pose is known to well under a millimetre but not exactly
    assert 1e-5 < np.sqrt(traces[0]) < 5e-3


# ---- pvnet ------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def pvnet_frames():
    """Three rendered frames of the default object (pvnet-eval's frames, a seed of their own) and
    the same frames degraded: blurred, with strong pixel noise, through JPEG at quality 40."""
    pytest.importorskip("onnxruntime")
    import cv2

    from flextrack import assets
    from flextrack.training import evaluate

    if not assets.pvnet_model_path().is_file():
        pytest.skip("no shipped pvnet model")
    frames = list(evaluate.rendered_frames(assets.default_object_model(), 3, seed=4242, scenes=1))
    rng = np.random.default_rng(0)
    degraded = []
    for _, rgb, camera, T, _ in frames:
        bad = cv2.GaussianBlur(rgb, (0, 0), 1.2).astype(float) + rng.normal(0, 12, rgb.shape)
        _, jpg = cv2.imencode(".jpg", np.clip(bad, 0, 255).astype(np.uint8), [cv2.IMWRITE_JPEG_QUALITY, 40])
        degraded.append(cv2.imdecode(jpg, cv2.IMREAD_UNCHANGED))
    return [(rgb, bad, camera, T) for (_, rgb, camera, T, _), bad in zip(frames, degraded)]


def _pvnet(refine: bool):
    from estimators.objects import ObjectRegistry, load_object
    from estimators.pvnet import PvnetEstimator
    from flextrack import assets

    obj = load_object("default", assets.default_object_model())
    return PvnetEstimator(ObjectRegistry([obj]), assets.pvnet_model_path(), refine=refine)


def test_pvnet_refined_pose_covariance_is_spd_and_grows_on_degraded_frames(pvnet_frames):
    """The refinement's covariance follows how well the outline sits on its edges."""
    pvnet = _pvnet(refine=True)
    grew, compared = 0, 0
    for i, (rgb, bad, camera, _) in enumerate(pvnet_frames):
        clean = pvnet.estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=camera, image=rgb))
        worse = pvnet.estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=camera, image=bad))
        assert clean.status is Status.OK, clean.message
        for out in (clean, worse):
            if out.status is Status.OK:
                assert_spd(out.covariance)
        if worse.status is Status.OK:
            compared += 1
            grew += np.trace(worse.covariance[3:, 3:]) > np.trace(clean.covariance[3:, 3:])
    assert compared >= 2 and grew == compared


def test_pvnet_keypoint_covariance_is_spd_and_grows_with_distance(pvnet_frames):
    """Without the refinement, PnP's pose on the voted keypoints: a farther object, a less certain pose
    (the voted keypoints' spread barely changes with these degradations: the network's vector field,
    not the pixels, makes most of it)."""
    pvnet = _pvnet(refine=False)
    by_distance = []
    for i, (rgb, bad, camera, T) in enumerate(pvnet_frames):
        for image in (rgb, bad):
            out = pvnet.estimate(EstimateInput(frame_id=i, capture_time_ns=0, camera=camera, image=image))
            assert out.status is Status.OK, out.message
            assert_spd(out.covariance)
        by_distance.append((T[2, 3], np.trace(out.covariance[3:, 3:])))
    traces = [tr for _, tr in sorted(by_distance)]
    assert max(d for d, _ in by_distance) - min(d for d, _ in by_distance) > 0.3
    assert traces == sorted(traces)
