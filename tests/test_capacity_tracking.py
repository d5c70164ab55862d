"""`flextrack bench capacity --tracking`: the frames a tracking device sends, each with its prior and cut to the
SDK's crop around it, answered by the chained tracking backend (in-process service, a short rendered sequence)."""

import numpy as np

from estimators.registry import EstimatorRegistry
from flextrack import assets
from flextrack.benchmarks.capacity_bench import TRACKING_STATE_BYTES, _tracking_workload
from flextrack.simulator.generate import generate_sequence
from flextrack.v1 import pose_estimation_pb2 as pb
from service.estimation import EstimationService


def test_tracking_frames_carry_a_prior_and_the_crop_around_it_and_are_answered(tmp_path):
    root = generate_sequence("translational", "medium", tmp_path / "seq", duration_s=0.2, fps=10.0, seed=3,
                             render=True)
    work = _tracking_workload(root, "pvnet_region", max_frames=3)
    requests = [pb.EstimateRequest.FromString(work.request(0, i)) for i in range(len(work.templates))]
    assert requests and all(r.HasField("prior") and len(r.client_state) == TRACKING_STATE_BYTES for r in requests)
    for r in requests:
        assert (r.image.width, r.image.height) == (r.crop.width, r.crop.height)
        assert r.crop.width * r.crop.height < 0.5 * r.intrinsics.width * r.intrinsics.height
    service = EstimationService(EstimatorRegistry.from_config(assets.default_config_path()))
    answers = [service.answer(r) for r in requests]
    assert all(a.status == pb.EstimateResponse.OK for a in answers), [a.message for a in answers]
    assert np.all(np.isfinite([a.pose.tz for a in answers]))
