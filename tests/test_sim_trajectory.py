"""Motion programs: exact derivatives, a still start, Table 3's figures, the object kept in view."""

import numpy as np
import pytest

from flextrack.geometry import so3
from flextrack.geometry.camera import PinholeCamera
from flextrack.simulator.trajectory import TABLE3, MotionProgram

PROGRAMS = list(TABLE3)


@pytest.mark.parametrize("motion,level", PROGRAMS)
def test_derivatives_are_exact(motion, level):
    prog = MotionProgram(motion, level, seed=3)
    t, h = np.array([2.5, 3.1, 9.7, 21.3, 31.0]), 1e-5
    k, kp, km = prog.camera(t), prog.camera(t + h), prog.camera(t - h)
    assert np.allclose((kp.p_WX - km.p_WX) / (2 * h), k.v_WX, atol=1e-8)
    assert np.allclose((kp.v_WX - km.v_WX) / (2 * h), k.a_WX, atol=1e-7)
    w_fd = np.array([so3.log(k.R_WX[i].T @ kp.R_WX[i]) - so3.log(k.R_WX[i].T @ km.R_WX[i])
                     for i in range(len(t))]) / (2 * h)
    assert np.allclose(w_fd, k.w_X, atol=1e-8)
    assert np.allclose((kp.w_X - km.w_X) / (2 * h), k.alpha_X, atol=1e-7)
    assert np.allclose(k.R_WX @ k.R_WX.transpose(0, 2, 1), np.eye(3), atol=1e-12)


@pytest.mark.parametrize("motion,level", PROGRAMS)
def test_still_start_then_smooth_motion(motion, level):
    prog = MotionProgram(motion, level, seed=1)
    still = prog.camera(np.linspace(0.0, prog.still_s, 50))
    for arr in (still.v_WX, still.a_WX, still.w_X, still.alpha_X):
        assert np.abs(arr).max() < 1e-12
    assert np.ptp(still.p_WX, axis=0).max() < 1e-12
    moving = prog.camera(np.linspace(prog.still_s + prog.ramp_s, prog.end_s, 50))
    assert np.linalg.norm(moving.v_WX, axis=1).mean() > 0.01


@pytest.mark.parametrize("motion,level", PROGRAMS)
def test_table3_statistics(motion, level):
    speed, (a_lo, a_hi), rate, (al_lo, al_hi) = TABLE3[(motion, level)]
    for seed in (0, 1, 2):
        stats = MotionProgram(motion, level, seed=seed).statistics(rate_hz=200.0)
        shaken, scripted = stats["with_shake"], stats["scripted"]
        assert abs(shaken["avg_speed_m_s"] / speed - 1) < 0.15
        assert abs(shaken["avg_angular_rate_rad_s"] / rate - 1) < 0.15
        lo, hi = scripted["accel_range_m_s2"]
        assert a_lo <= lo and hi < a_hi
        lo, hi = scripted["angular_accel_range_rad_s2"]
        if al_hi == 0:
            assert hi < 1e-9
        else:
            assert al_lo <= lo and hi < al_hi
        assert stats["table3"]["avg_speed_m_s"] == speed


@pytest.mark.parametrize("motion,level", PROGRAMS)
def test_object_stays_in_view_from_1_2_m_then_closer(motion, level):
    cam = PinholeCamera.linemod()
    prog = MotionProgram(motion, level, seed=5, target_W=np.array([0.0, 0.0, 0.05]))
    k = prog.camera(np.arange(0.0, prog.end_s, 0.05))
    target_C = np.einsum("nji,nj->ni", k.R_WX, prog.target_W - k.p_WX)
    uv = cam.project(target_C)
    margin = 100  # px: room for a 150 mm object at ~1 m around its centre
    assert (target_C[:, 2] > 0).all()
    assert (uv[:, 0] > margin).all() and (uv[:, 0] < cam.width - margin).all()
    assert (uv[:, 1] > margin).all() and (uv[:, 1] < cam.height - margin).all()
    distance = np.linalg.norm(target_C, axis=1)
    # starts 1.2 m away (the paper's initial distance), works closer once moving (PIA's area limit)
    assert abs(distance[0] - 1.2) < 1e-9 and distance.min() > 0.7 and distance.max() < 1.2 + 1e-9
    working = distance[np.arange(0.0, prog.end_s, 0.05) >= prog.still_s + prog.ramp_s]
    assert abs(np.median(working) - 0.95) < 0.05 and working.max() < 1.2


def test_short_program_reports_statistics_over_what_there_is():
    stats = MotionProgram("circular", "medium", duration_s=1.0).statistics(200.0)
    for part in ("scripted", "with_shake"):
        values = [v for x in stats[part].values() for v in np.atleast_1d(x)]
        assert np.all(np.isfinite(values))


def test_seeds_change_the_shake_not_the_script():
    a, b = MotionProgram("circular", "hard", seed=0), MotionProgram("circular", "hard", seed=1)
    t = np.linspace(5, 30, 200)
    assert not np.allclose(a.camera(t).w_X, b.camera(t).w_X)
    assert np.allclose(a.camera(t).w_X, MotionProgram("circular", "hard", seed=0).camera(t).w_X)
    sa, sb = a.statistics(200.0)["scripted"], b.statistics(200.0)["scripted"]
    assert sa["avg_speed_m_s"] == pytest.approx(sb["avg_speed_m_s"], rel=1e-9)


def test_unknown_program_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown motion program"):
        MotionProgram("spiral", "easy")
