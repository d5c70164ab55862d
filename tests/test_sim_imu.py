"""The IMU agrees with the trajectory (integrated back to it) and its noise is what is configured."""

import numpy as np
import pytest

from flextrack.geometry import se3, so3
from flextrack.simulator import imu
from flextrack.simulator.generate import T_BC_PHONE
from flextrack.simulator.integrate import integrate
from flextrack.simulator.statistics import allan_deviation, expected_adev
from flextrack.simulator.trajectory import TABLE3, MotionProgram

T_CB = se3.inverse(T_BC_PHONE)


def _max_errors(result, body) -> tuple[float, float]:
    pos_mm = 1000 * np.linalg.norm(result.p_WB - body.p_WX, axis=1).max()
    dR = np.einsum("nji,njk->nik", body.R_WX, result.R_WB)
    rot_deg = np.degrees(np.linalg.norm([so3.log(R) for R in dR[::25]], axis=1).max())
    return pos_mm, rot_deg


@pytest.mark.parametrize("motion,level", list(TABLE3))
@pytest.mark.parametrize("rate,pos_tol_mm,rot_tol_deg", [(1000.0, 1.0, 0.01), (200.0, 5.0, 0.05)])
def test_integrating_ideal_imu_reproduces_trajectory(motion, level, rate, pos_tol_mm, rot_tol_deg):
    prog = MotionProgram(motion, level, seed=0)
    t = imu.sample_times(0.0, prog.end_s, rate)
    body = prog.camera(t).attached(T_CB)
    record = imu.synthesize(t, body, imu.profile("ideal", rate), np.random.default_rng(0))
    result = integrate(t, record.imu.gyro, record.imu.accel, body.R_WX[0], body.p_WX[0], body.v_WX[0])
    pos_mm, rot_deg = _max_errors(result, body)
    assert pos_mm < pos_tol_mm and rot_deg < rot_tol_deg


def test_integrator_with_exact_signal_and_jittered_samples():
    prog = MotionProgram("circular", "hard", seed=2)

    def exact(tq):
        body = prog.camera(tq).attached(T_CB)
        return body.w_X, body.specific_force()

    t = imu.sample_times(0.0, prog.end_s, 200.0, jitter_s=5e-4, rng=np.random.default_rng(1))
    assert np.all(np.diff(t) > 0)
    body = prog.camera(t).attached(T_CB)
    gyro, accel = exact(t)
    result = integrate(t, gyro, accel, body.R_WX[0], body.p_WX[0], body.v_WX[0], imu_at=exact)
    pos_mm, rot_deg = _max_errors(result, body)
    assert pos_mm < 0.1 and rot_deg < 1e-3


def test_static_imu_reads_gravity_and_biases_are_removed_by_integration():
    prog = MotionProgram("static", "easy", seed=0, duration_s=5.0)
    t = imu.sample_times(0.0, prog.end_s, 200.0)
    body = prog.camera(t).attached(T_CB)
    assert np.allclose(np.linalg.norm(body.specific_force(), axis=1), 9.81)
    prof = imu.profile("pixel2", 200.0)
    record = imu.synthesize(t, body, prof, np.random.default_rng(4))
    result = integrate(t, record.imu.gyro, record.imu.accel, body.R_WX[0], body.p_WX[0], body.v_WX[0],
                       bias_gyro=record.bias_gyro, bias_accel=record.bias_accel)
    pos_mm, rot_deg = _max_errors(result, body)
    assert pos_mm < 50 and rot_deg < 0.05  # only white noise left: a few mm over 7 s


@pytest.mark.parametrize("name", ["pixel2", "euroc"])
def test_white_noise_std_and_bias_walk_match_profile(name):
    rate = 200.0
    prof = imu.profile(name, rate)
    t = imu.sample_times(0.0, 300.0, rate)
    prog = MotionProgram("static", "easy", seed=0, still_s=1.0, duration_s=299.0)
    body = prog.camera(t).attached(T_CB)
    record = imu.synthesize(t, body, prof, np.random.default_rng(7))
    n = prof.noise
    gyro_noise = record.imu.gyro - body.w_X - record.bias_gyro
    accel_noise = record.imu.accel - body.specific_force() - record.bias_accel
    assert np.allclose(gyro_noise.std(axis=0), n.gyroscope_noise_density * np.sqrt(rate), rtol=0.05)
    assert np.allclose(accel_noise.std(axis=0), n.accelerometer_noise_density * np.sqrt(rate), rtol=0.05)
    # bias random walk: increments have std rw * sqrt(dt)
    steps = np.diff(record.bias_gyro, axis=0).std()
    assert steps == pytest.approx(n.gyroscope_random_walk / np.sqrt(rate), rel=0.05)
    steps = np.diff(record.bias_accel, axis=0).std()
    assert steps == pytest.approx(n.accelerometer_random_walk / np.sqrt(rate), rel=0.05)


def test_turn_on_bias_spread_matches_profile():
    prof = imu.profile("pixel2", 200.0)
    t = imu.sample_times(0.0, 0.01, 200.0)
    body = MotionProgram("static", "easy").camera(t).attached(T_CB)
    starts = np.array([imu.synthesize(t, body, prof, np.random.default_rng(s)).bias_gyro[0] for s in range(400)])
    assert starts.std() == pytest.approx(prof.gyro_bias_sigma, rel=0.1)


def test_allan_deviation_shows_densities():
    """At tau = 1 s the Allan deviation reads sqrt(N^2 + K^2/3); its short-tau slope is -1/2."""
    rate = 200.0
    prof = imu.profile("pixel2", rate)
    t = imu.sample_times(0.0, 120.0, rate)
    body = MotionProgram("static", "easy", still_s=1.0, duration_s=119.0).camera(t).attached(T_CB)
    record = imu.synthesize(t, body, prof, np.random.default_rng(11))
    n = prof.noise
    for data, density, walk in ((record.imu.gyro, n.gyroscope_noise_density, n.gyroscope_random_walk),
                                (record.imu.accel, n.accelerometer_noise_density, n.accelerometer_random_walk)):
        taus, adev = allan_deviation(data, rate, np.array([0.02, 0.2, 1.0]))
        level = adev.mean(axis=1)
        assert level[2] == pytest.approx(expected_adev(1.0, density, walk), rel=0.1)
        slope = np.log(level[1] / level[0]) / np.log(taus[1] / taus[0])
        assert slope == pytest.approx(-0.5, abs=0.05)


def test_unknown_profile_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown IMU profile"):
        imu.profile("iphone", 200.0)
