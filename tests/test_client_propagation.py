"""PPM: the scalar Rodrigues kernel, propagation of exact IMU, and pose_at at any time."""

import numpy as np
import pytest

from client_sdk import ResponseOutcome, TrackerOptions
from client_sdk.propagation import rotate, step_midpoint, step_paper
from flextrack.geometry import so3
from flextrack.geometry.metrics import proj_px, re_deg, te_mm
from flextrack.testing.tracker_world import BOX_O, CAMERA, G_O, Motion, drive


def test_rotate_matches_so3_exp_for_small_and_large_angles():
    rng = np.random.default_rng(1)
    for scale in (1e-9, 1e-5, 1e-3, 0.1, 2.0):
        for _ in range(20):
            R0 = so3.exp(rng.normal(size=3))
            w = rng.normal(size=3) * scale
            got = np.array(rotate(tuple(R0.ravel()), *w)).reshape(3, 3)
            assert np.allclose(got, R0 @ so3.exp(w), atol=1e-13)


def test_paper_step_is_rotation_then_velocity_then_position():
    x = tuple(np.eye(3).ravel()) + (1.0, 2.0, 3.0) + (0.1, 0.2, 0.3)
    c = (0.01, 0.0, 0.0) + (0.0, 0.0, 0.1) + (0.0, 0.0, -9.81)
    s1 = (10_000_000, 0.51, 0.0, 0.0, 0.0, 0.0, 10.0)  # 10 ms later
    out = step_paper(x, c, 0, 10_000_000, s1, s1)
    R = so3.exp(np.array([0.005, 0.0, 0.0]))
    v = np.array([0.1, 0.2, 0.3]) + 0.01 * (R @ np.array([0.0, 0.0, 9.9]) + np.array([0.0, 0.0, -9.81]))
    assert np.allclose(np.array(out[0:9]).reshape(3, 3), R, atol=1e-15)
    assert np.allclose(out[12:15], v, atol=1e-15)
    assert np.allclose(out[9:12], np.array([1.0, 2.0, 3.0]) + 0.01 * v, atol=1e-15)


def test_midpoint_is_exact_for_constant_rates():
    """Constant body rate and constant acceleration in O: the midpoint step is exact in p and v."""
    x = tuple(np.eye(3).ravel()) + (0.0,) * 6
    c = (0.0,) * 6 + tuple(G_O)
    s = (5_000_000, 0.0, 0.0, 0.0) + tuple(-G_O + np.array([0.3, 0.0, 0.0]))
    out = step_midpoint(x, c, 0, 5_000_000, s, s)
    dt = 5e-3
    assert np.allclose(out[12:15], [0.3 * dt, 0, 0], atol=1e-15)
    assert np.allclose(out[9:12], [0.5 * 0.3 * dt * dt, 0, 0], atol=1e-15)


@pytest.mark.parametrize("integrator, max_mm", [("paper", 10.0), ("midpoint", 0.05)])
def test_pure_propagation_follows_the_trajectory(integrator, max_mm):
    """One backend pose to initialise, then IMU only for ~3 s of motion with exact IMU readings."""
    m = Motion()
    run = drive(m, TrackerOptions(fusion="paper", integrator=integrator, backend_after_init=False), duration_s=4.0)
    tr = run.tracker
    assert np.allclose(tr.state.g_O, G_O, atol=1e-6)  # gravity from the still start
    t = tr.now_ns
    T, G = tr.pose_at(t), m.T_CO(t * 1e-9)
    assert te_mm(T, G) < max_mm
    assert re_deg(T, G) < 0.05
    assert tr.outcomes[ResponseOutcome.INITIALIZED] == 1 and tr.outcomes[ResponseOutcome.APPLIED] == 0


def test_midpoint_is_far_more_accurate_than_paper_integration():
    m = Motion()
    err = {}
    for integrator in ("paper", "midpoint"):
        tr = drive(m, TrackerOptions(fusion="paper", integrator=integrator, backend_after_init=False), duration_s=4.0).tracker
        err[integrator] = te_mm(tr.pose_at(tr.now_ns), m.T_CO(tr.now_ns * 1e-9))
    assert err["midpoint"] < err["paper"] / 50


def test_pose_at_any_time_and_rate():
    """Output at 240 FPS (off the IMU grid) and at IMU times stays on the trajectory with a GT backend."""
    m = Motion()
    tr = drive(m, TrackerOptions(fusion="paper", ), duration_s=4.0).tracker
    now = tr.now_ns
    times = np.arange(now - int(1.9e9), now, int(1e9 / 240))
    errs = [proj_px(tr.pose_at(int(t)), m.T_CO(t * 1e-9), CAMERA, BOX_O) for t in times]
    assert max(errs) < 0.1
    # a short extrapolation past the newest sample holds its rates: still close
    assert proj_px(tr.pose_at(now + 3_000_000), m.T_CO(now * 1e-9 + 3e-3), CAMERA, BOX_O) < 0.1
    with pytest.raises(ValueError):
        tr.pose_at(now - int(3e9))  # older than the 2 s buffer


def test_pose_at_is_continuous_across_imu_samples():
    m = Motion()
    tr = drive(m, TrackerOptions(fusion="paper", integrator="midpoint"), duration_s=3.0).tracker
    t = tr.now_ns - 100_000_000
    t = t - t % 5_000_000  # an IMU sample time
    before, at, after = tr.pose_at(t - 1), tr.pose_at(t), tr.pose_at(t + 1)
    assert te_mm(before, at) < 1e-3 and te_mm(at, after) < 1e-3
