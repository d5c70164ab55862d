import numpy as np

from flextrack.geometry import se3, so3


def test_exp_log_roundtrip_and_quaternions():
    rng = np.random.default_rng(0)
    for _ in range(200):
        phi = rng.normal(size=3) * rng.uniform(0, 3)
        R = so3.exp(phi)
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.allclose(so3.exp(so3.log(R)), R, atol=1e-9)
        q = so3.quat_from_matrix(R)
        assert np.allclose(so3.matrix_from_quat(q), R, atol=1e-12)


def test_interpolation_endpoints_and_midpoint():
    T0 = se3.make(so3.exp([0, 0, 0.2]), [0, 0, 1])
    T1 = se3.make(so3.exp([0, 0, 0.6]), [0.2, 0, 1])
    mid = se3.interpolate(T0, T1, 0.5)
    assert np.allclose(mid[:3, :3], so3.exp([0, 0, 0.4]))
    assert np.allclose(mid[:3, 3], [0.1, 0, 1])
    times = np.array([0, 10], dtype=np.int64)
    assert se3.interpolate_at(times, np.stack([T0, T1]), 11) is None
    assert np.allclose(se3.interpolate_at(times, np.stack([T0, T1]), 5), mid)
