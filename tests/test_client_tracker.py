"""The Tracker state machine: initialisation, the PRM's requests, PIM failures, bad input, determinism."""

import subprocess
import sys

import numpy as np
import pytest

from client_sdk import ResponseOutcome, Status, Tracker, TrackerOptions
from client_sdk import state as state_codec
from client_sdk.propagation import propagate, step_paper
from flextrack.geometry import se3, so3
from flextrack.geometry.metrics import proj_px
from flextrack.testing.tracker_world import BOX_O, CAMERA, G_O, T_BC, Motion, drive

MS = 1_000_000
G_B = np.array([0.3, -9.7, 1.2])  # a still device: the accelerometer reads -g_B


def _still(tracker, t_from_ms, t_to_ms, gyro=(0.001, -0.002, 0.003)):
    for t in range(t_from_ms, t_to_ms + 1, 5):
        tracker.add_imu(t * MS, gyro, -G_B)


def _tracker(**kw):
    return Tracker(TrackerOptions(**kw), CAMERA, T_BC, BOX_O)


T_CO_0 = se3.make(np.eye(3), np.array([0.0, 0.0, 0.6]))


def _initialised():
    tr = _tracker()
    _still(tr, 5, 600)
    req = tr.add_frame(600 * MS).request
    assert tr.on_backend_response(req.request_id, req.frame_t_ns, T_CO_0) is ResponseOutcome.INITIALIZED
    return tr


def test_initialisation_statuses_and_first_pose():
    tr = _tracker()
    r = tr.add_frame(1 * MS)
    assert (r.status, r.T_CO, r.request) == (Status.INITIALIZING, None, None)
    assert "waiting for IMU" in tr.status_detail
    _still(tr, 5, 300)
    assert tr.add_frame(300 * MS).request is None and "collecting IMU" in tr.status_detail
    _still(tr, 305, 600)
    req = tr.add_frame(600 * MS).request
    assert req is not None and req.reason == "init" and req.frame_t_ns == 600 * MS
    r = tr.add_frame(610 * MS)
    assert r.request is None and "waiting for the first backend pose" in tr.status_detail
    # a lost request is re-sent; a backend that finds nothing is asked again
    assert tr.on_backend_failure(req.request_id) and not tr.on_backend_failure(req.request_id)
    req2 = tr.add_frame(620 * MS).request
    assert req2.request_id != req.request_id
    assert tr.on_backend_response(req2.request_id, req2.frame_t_ns, None, ok=False) is ResponseOutcome.REJECTED
    assert not tr.initialized and tr.pose_at(620 * MS) is None
    req3 = tr.add_frame(630 * MS).request
    assert tr.on_backend_response(req3.request_id, req3.frame_t_ns, T_CO_0) is ResponseOutcome.INITIALIZED
    st = tr.state
    assert np.allclose(st.b_g, [0.001, -0.002, 0.003])
    R_OB = (se3.inverse(T_CO_0) @ se3.inverse(T_BC))[:3, :3]
    assert np.allclose(st.g_O, R_OB @ G_B) and np.allclose(st.v_OB, 0.0) and np.allclose(st.b_a, 0.0)
    # still device, exact gravity: the pose stays put
    assert np.allclose(tr.pose_at(630 * MS), T_CO_0, atol=1e-12)
    r = tr.add_frame(640 * MS)
    assert r.status is Status.FINE and r.request.reason == "refine"
    assert np.allclose(r.T_CO, T_CO_0, atol=1e-9)


def test_initialisation_waits_for_a_still_device():
    m = Motion(still_s=0.0)  # moving from the start
    run = drive(m, TrackerOptions(fusion="paper", ), duration_s=1.5)
    assert not run.tracker.initialized and "hold the device still" in run.tracker.status_detail
    assert all(r.request is None for r in run.results)
    run = drive(m, TrackerOptions(fusion="paper", init_require_still=False), duration_s=1.5)
    assert run.tracker.initialized


def test_one_request_in_flight_and_stale_responses():
    tr = _initialised()
    _still(tr, 605, 650)
    req = tr.add_frame(650 * MS).request
    assert tr.add_frame(660 * MS).request is None and tr.in_flight == req
    before = tr.state_bytes()
    assert tr.on_backend_response(req.request_id + 7, req.frame_t_ns, T_CO_0) is ResponseOutcome.STALE
    assert tr.state_bytes() == before
    with pytest.raises(ValueError, match="capture time"):
        tr.on_backend_response(req.request_id, req.frame_t_ns + 1, T_CO_0)
    with pytest.raises(ValueError, match="rigid"):
        tr.on_backend_response(req.request_id, req.frame_t_ns, np.diag([2.0, 1.0, 1.0, 1.0]))
    assert tr.in_flight == req and tr.state_bytes() == before
    assert tr.on_backend_response(req.request_id, req.frame_t_ns, T_CO_0) is ResponseOutcome.APPLIED
    assert tr.in_flight is None and tr.add_frame(670 * MS).request is not None


def test_responses_older_than_the_imu_buffer_are_dropped():
    tr = _initialised()
    req = tr.add_frame(700 * MS).request
    _still(tr, 605, 4000)  # 3.4 s later; the buffer keeps 2 s
    assert tr.on_backend_response(req.request_id, req.frame_t_ns, T_CO_0) is ResponseOutcome.TOO_OLD
    assert "older than the IMU buffer" in tr.status_detail and tr.in_flight is None


def test_bad_imu_and_frames_are_rejected_without_state_change():
    tr = _initialised()
    _still(tr, 605, 700)
    before, n = tr.state_bytes(), tr.now_ns
    bad = [
        (705 * MS, (np.nan, 0, 0), (0, 0, 9.8)),
        (705 * MS, (0, 0, 0), (0, np.inf, 9.8)),
        (700 * MS, (0, 0, 0), (0, 0, 9.8)),  # same time as the previous sample
        (650 * MS, (0, 0, 0), (0, 0, 9.8)),  # out of order
        (705.5 * MS, (0, 0, 0), (0, 0, 9.8)),  # not integer nanoseconds
        (705 * MS, (0, 0), (0, 0, 9.8)),  # not 3 numbers
        (705 * MS, "abc", (0, 0, 9.8)),
    ]
    for t, g, a in bad:
        with pytest.raises(ValueError):
            tr.add_imu(t, g, a)
    assert tr.state_bytes() == before and tr.now_ns == n
    tr.add_frame(710 * MS)
    with pytest.raises(ValueError):
        tr.add_frame(710 * MS)
    with pytest.raises(ValueError):
        _tracker(integrator="rk4")
    with pytest.raises(ValueError):
        _tracker(fps=-1.0)
    with pytest.raises(ValueError):
        Tracker(TrackerOptions(), CAMERA, np.eye(3), BOX_O)


def test_same_events_give_identical_outputs():
    kw = {"duration_s": 3.0, "b_g": (0.002, 0.0, -0.001), "b_a": (0.02, 0.0, 0.01), "gyro_sigma": 1e-3,
          "accel_sigma": 1e-2, "seed": 4}
    a, b = drive(Motion(), TrackerOptions(fusion="paper", ), **kw), drive(Motion(), TrackerOptions(fusion="paper", ), **kw)
    assert [r.request for r in a.results] == [r.request for r in b.results]
    assert all(np.array_equal(x, y) for x, y in zip(a.poses, b.poses) if x is not None)
    assert a.statuses == b.statuses and a.tracker.state_bytes() == b.tracker.state_bytes()


def test_state_bytes_are_about_10_kB_and_decode():
    run = drive(Motion(), TrackerOptions(fusion="paper", ), duration_s=2.0)
    blob = run.tracker.state_bytes()
    assert 9_000 < len(blob) < 11_000
    st, imu = state_codec.decode(blob)
    ref = run.tracker.state
    assert st.t_ns == ref.t_ns and np.array_equal(st.as_vector(), ref.as_vector())
    assert imu.shape == (176, 7) and imu[-1, 0] <= 0.0
    with pytest.raises(ValueError):
        state_codec.decode(blob[:-8])
    assert len(_tracker().state_bytes()) > 0  # before initialisation too


def test_response_resets_the_state_and_repropagates_the_buffer():
    """After a response, the state now == the backend pose at t0 propagated through the kept IMU."""
    m, log = Motion(), []
    run = drive(m, TrackerOptions(fusion="paper", ), duration_s=3.0, b_g=(0.003, 0, 0), b_a=(0, 0.02, 0), imu_log=log)
    tr = run.tracker
    req = tr.in_flight or tr.add_frame(int(run.times_ns[-1]) + MS).request
    t = log[-1][0]
    for _ in range(10):  # 50 ms of IMU before the answer
        t += 5 * MS
        w, f = m.imu(t * 1e-9)
        tr.add_imu(t, w, f)
        log.append((t, w, f))
    t0 = req.frame_t_ns
    assert tr.on_backend_response(req.request_id, t0, m.T_CO(t0 * 1e-9)) is ResponseOutcome.APPLIED
    R, p = m.body_pose(t0 * 1e-9)
    st = tr.state
    x0 = tuple(R.ravel()) + tuple(p) + tuple(tr.last_bscm.v)
    c = tuple(st.b_g) + tuple(st.b_a) + tuple(st.g_O)
    samples = [(ti,) + tuple(map(float, w)) + tuple(map(float, f)) for ti, w, f in log]
    start = next(i for i, s in enumerate(samples) if s[0] > t0)
    x = propagate(step_paper, x0, c, t0, samples, [None] * len(samples), start)
    assert np.allclose(np.array(x[0:9]).reshape(3, 3), st.R_OB, atol=1e-12)
    assert np.allclose(x[9:12], st.p_OB, atol=1e-12) and np.allclose(x[12:15], st.v_OB, atol=1e-12)


def test_wrong_pose_abandons_the_regular_request_and_sends_the_frame_at_once():
    m = Motion()
    run = drive(m, TrackerOptions(fusion="paper", ), duration_s=3.0)
    tr = run.tracker
    t = tr.now_ns
    regular = tr.in_flight or tr.add_frame(int(run.times_ns[-1]) + MS).request
    assert regular.reason == "refine"
    w, f = m.imu((t + 5 * MS) * 1e-9)
    tr.add_imu(t + 5 * MS, w + np.array([0.0, 40.0, 0.0]), f)  # a gyro glitch: 0.2 rad in one sample
    r = tr.add_frame(t + 6 * MS)
    assert r.status is Status.WRONG_POSE and "corner offset" in tr.status_detail
    assert r.request is not None and r.request.reason == "failure" and r.request.frame_t_ns == t + 6 * MS
    assert tr.on_backend_response(regular.request_id, regular.frame_t_ns, m.T_CO(regular.frame_t_ns * 1e-9)) \
        is ResponseOutcome.STALE
    tr.add_imu(t + 10 * MS, *m.imu((t + 10 * MS) * 1e-9))
    before = tr.last_bscm
    assert tr.on_backend_response(r.request.request_id, r.request.frame_t_ns, m.T_CO((t + 6 * MS) * 1e-9)) \
        is ResponseOutcome.APPLIED
    assert tr.last_bscm is before  # the PRM was reset: no BSCM across the failure
    r2 = tr.add_frame(t + 12 * MS)
    assert proj_px(r2.T_CO, m.T_CO((t + 12 * MS) * 1e-9), CAMERA, BOX_O) < 0.5


def test_tracking_lost_sends_one_request_at_a_time_and_recovers():
    m = Motion()
    far = se3.make(np.eye(3), np.array([0.0, 0.0, 30.0]))
    calls = {"n": 0}

    def answer(t):  # one absurd backend answer (the object 30 m away) after 2 s
        if t > 2.0 and calls["n"] == 0:
            calls["n"] = 1
            return far
        return m.T_CO(t)

    run = drive(m, TrackerOptions(fusion="paper", ), duration_s=3.0, answer=answer)
    lost = [i for i, s in enumerate(run.statuses) if s is Status.TRACKING_LOST]
    assert lost, "the far pose must be reported lost"
    reqs = [run.results[i].request for i in lost if run.results[i].request]
    assert len(reqs) == 1 and reqs[0].reason == "failure"  # no request storm while lost
    assert run.statuses[-1] is Status.FINE
    assert proj_px(run.poses[-1], m.T_CO(run.times_ns[-1] * 1e-9), CAMERA, BOX_O) < 0.5


def test_ablation_switches():
    m = Motion()
    kw = {"duration_s": 5.0, "b_g": (0.01, -0.02, 0.015), "b_a": (0.05, -0.08, 0.1), "bias_from_s": 1.0}
    full = drive(m, TrackerOptions(fusion="paper", ), **kw)
    no_bscm = drive(m, TrackerOptions(fusion="paper", bscm=False, pia=False), **kw)
    imu_only = drive(m, TrackerOptions(fusion="paper", backend_after_init=False), **kw)

    def err(run):
        return np.mean([proj_px(T, m.T_CO(t * 1e-9), CAMERA, BOX_O) for t, T in zip(run.times_ns, run.poses)
                        if T is not None])

    assert np.allclose(no_bscm.tracker.state.b_a, 0.0) and np.allclose(no_bscm.tracker.state.b_g, 0.0)
    assert not np.allclose(full.tracker.state.b_g, 0.0)
    assert sum(r.request is not None for r in imu_only.results) == 1
    assert err(no_bscm) > 2 * err(full) and err(imu_only) > 10 * err(no_bscm)
    assert set(no_bscm.statuses) <= {Status.INITIALIZING, Status.FINE}  # PIA off: never a failure


def test_client_sdk_imports_nothing_heavy():
    code = ("import sys, client_sdk, client_sdk.tracker; "
            "bad = [m for m in ('scipy', 'cv2', 'torch', 'onnxruntime', 'service', 'estimators', 'flextrack.simulator', "
            "'matplotlib', 'trimesh', 'pyrender') if m in sys.modules]; print(bad); sys.exit(1 if bad else 0)")
    out = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True)
    assert out.returncode == 0, out.stdout + out.stderr


def test_a_silent_backend_turns_the_pose_lost_and_a_fresh_pose_brings_it_back():
    tr = _initialised()  # last backend pose captured at 600 ms
    _still(tr, 605, 1500)
    req = tr.add_frame(1500 * MS).request
    assert tr.status is Status.FINE and req is not None
    assert tr.on_backend_failure(req.request_id)  # the server is gone
    _still(tr, 1505, 1700)
    r = tr.add_frame(1700 * MS)  # 1.1 s without a backend pose
    assert r.status is Status.TRACKING_LOST and "no backend pose" in tr.status_detail
    assert r.request is not None and r.request.reason == "failure"
    assert tr.on_backend_response(r.request.request_id, r.request.frame_t_ns, T_CO_0) is ResponseOutcome.APPLIED
    _still(tr, 1705, 1710)
    assert tr.add_frame(1710 * MS).status is Status.FINE
    # the IMU-only ablation expects no backend, so it never calls that lost
    tr = _tracker(backend_after_init=False)
    _still(tr, 5, 600)
    req = tr.add_frame(600 * MS).request
    tr.on_backend_response(req.request_id, req.frame_t_ns, T_CO_0)
    _still(tr, 605, 3000)
    assert tr.add_frame(3000 * MS).status is Status.FINE


def _serve(tr, t_from_ms, t_to_ms, answer=lambda t_ms: T_CO_0, latency_ms=50):
    """Still IMU, a frame every 10 ms, each request answered `latency_ms` later with answer(capture ms)."""
    pending, statuses = [], []
    for t in range(t_from_ms, t_to_ms + 1, 10):
        _still(tr, t - 5, t)
        for due, req in [p for p in pending if p[0] <= t]:
            pending.remove((due, req))
            tr.on_backend_response(req.request_id, req.frame_t_ns, answer(req.frame_t_ns // MS))
        r = tr.add_frame(t * MS)
        statuses.append(r.status)
        if r.request is not None:
            pending.append((t + latency_ms, r.request))
    return statuses


SHIFTED = se3.make(np.eye(3), np.array([0.6, 0.0, 0.6]))  # 0.6 m to the side of T_CO_0


def _respond(tr, t_ms, T_CO):
    _still(tr, t_ms - 95, t_ms)
    req = tr.add_frame(t_ms * MS).request
    return tr.on_backend_response(req.request_id, req.frame_t_ns, T_CO)


def test_two_poses_implying_an_impossible_speed_do_not_set_the_velocity():
    tr = _initialised()  # still, T_CO_0 at 600 ms
    _respond(tr, 700, SHIFTED)  # disagrees with the IMU beyond belief: applied, PRM reset
    assert "disagrees" in tr.status_detail
    _respond(tr, 800, T_CO_0)  # the new BSCM reference
    _respond(tr, 900, SHIFTED)  # 0.6 m in 0.1 s: 6 m/s from two poses, one of them wrong
    assert "imply 6.0 m/s" in tr.status_detail
    assert np.linalg.norm(tr.state.v_OB) < 0.1
    # without the limit the velocity would have been set to 6 m/s
    tr = _tracker(max_speed_m_s=100.0)
    _still(tr, 5, 600)
    req = tr.add_frame(600 * MS).request
    tr.on_backend_response(req.request_id, req.frame_t_ns, T_CO_0)
    for t, T in ((700, SHIFTED), (800, T_CO_0), (900, SHIFTED)):
        _respond(tr, t, T)
    assert np.linalg.norm(tr.state.v_OB) > 5.0


def test_a_wrong_velocity_is_re_estimated_while_the_frames_keep_failing():
    """Frames that go on failing must not keep resetting the PRM, or the velocity is never fixed."""
    tr = _tracker(max_speed_m_s=100.0)
    _still(tr, 5, 600)
    req = tr.add_frame(600 * MS).request
    tr.on_backend_response(req.request_id, req.frame_t_ns, T_CO_0)
    for t, T in ((700, SHIFTED), (800, T_CO_0), (900, SHIFTED)):
        _respond(tr, t, T)  # leaves a 6 m/s velocity on a still device
    statuses = _serve(tr, 910, 1600)
    assert statuses[0] is not Status.FINE  # the wrong velocity is caught ...
    assert set(statuses[-20:]) == {Status.FINE}  # ... and fixed by the poses that follow
    assert proj_px(tr.pose_at(1600 * MS), T_CO_0, CAMERA, BOX_O) < 1.0


def _flipped(T_CO):
    """The pose turned 108 degrees about the object's own z axis: a vision backend's gross error."""
    return T_CO @ se3.make(so3.exp(np.array([0.0, 0.0, np.radians(108.0)])), np.zeros(3))


def test_the_backend_gate_ignores_a_flipped_pose_and_gives_way_to_a_persistent_one():
    m = Motion()
    flips = {"n": 0}

    def one_flip(t):
        if t > 2.0 and flips["n"] == 0:
            flips["n"] = 1
            return _flipped(m.T_CO(t))
        return m.T_CO(t)

    gated = drive(m, TrackerOptions(fusion="paper", backend_gate_px=50.0), duration_s=3.0, answer=one_flip)
    assert gated.tracker.outcomes[ResponseOutcome.GATED] == 1
    assert set(gated.statuses) == {Status.INITIALIZING, Status.FINE}
    flips["n"] = 0
    trusting = drive(m, TrackerOptions(fusion="paper", ), duration_s=3.0, answer=one_flip)  # the paper: applied
    assert trusting.tracker.outcomes[ResponseOutcome.GATED] == 0

    def worst(run):
        return max(proj_px(T, m.T_CO(t * 1e-9), CAMERA, BOX_O) for t, T in zip(run.times_ns, run.poses)
                   if T is not None)

    assert worst(gated) < 1.0 and worst(trusting) > 20.0  # the PIA cannot see a pose set wrong
    for run in (gated, trusting):
        assert proj_px(run.poses[-1], m.T_CO(run.times_ns[-1] * 1e-9), CAMERA, BOX_O) < 0.5
    # a backend that keeps saying the same is believed after backend_gate_rejects poses
    moved = drive(m, TrackerOptions(fusion="paper", backend_gate_px=50.0), duration_s=3.0,
                  answer=lambda t: _flipped(m.T_CO(t)) if t > 2.0 else m.T_CO(t))
    assert moved.tracker.outcomes[ResponseOutcome.GATED] == 2
    assert proj_px(moved.poses[-1], _flipped(m.T_CO(moved.times_ns[-1] * 1e-9)), CAMERA, BOX_O) < 2.0


def test_the_backend_gate_refuses_a_pose_behind_the_camera_without_failing():
    """A pose with box corners behind the camera has no pixel distance to the tracked one: it is gated
    (it once raised a TypeError inside the tracker, in a pvnet replay)."""
    m = Motion()
    behind = {"n": 0}

    def once_behind(t):
        if t > 2.0 and behind["n"] == 0:
            behind["n"] = 1
            return se3.make(so3.exp(np.array([np.pi, 0.0, 0.0])), np.zeros(3)) @ m.T_CO(t)  # turned behind the camera
        return m.T_CO(t)

    run = drive(m, TrackerOptions(fusion="paper", backend_gate_px=50.0), duration_s=3.0, answer=once_behind)
    assert behind["n"] == 1 and run.tracker.outcomes[ResponseOutcome.GATED] == 1
    assert proj_px(run.poses[-1], m.T_CO(run.times_ns[-1] * 1e-9), CAMERA, BOX_O) < 0.5


def test_a_wrong_first_pose_is_overruled_and_gravity_re_anchored():
    """Initialised from a flipped pose, the tracker's gravity is wrong too; once the gate gives way to
    the backend's consistent answers, both are set right and tracking comes back."""
    m = Motion()
    first = {"t": None}

    def flipped_first(t):
        first["t"] = first["t"] or t
        return _flipped(m.T_CO(t)) if t == first["t"] else m.T_CO(t)

    run = drive(m, TrackerOptions(fusion="paper", backend_gate_px=50.0), duration_s=4.0, answer=flipped_first)
    assert run.tracker.outcomes[ResponseOutcome.GATED] >= 1
    g_O = run.tracker.state.g_O
    assert np.degrees(np.arccos(np.clip(g_O @ G_O / (np.linalg.norm(g_O) * np.linalg.norm(G_O)), -1, 1))) < 1.0
    assert proj_px(run.poses[-1], m.T_CO(run.times_ns[-1] * 1e-9), CAMERA, BOX_O) < 1.0
