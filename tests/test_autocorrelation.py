"""The standard error of a window's mean, with correlated samples counted for what they are worth."""

import numpy as np

from client_sdk import initialization
from client_sdk.options import TrackerOptions
from flextrack.autocorrelation import standard_error_of_mean


def _ar1(rng, n, phi, k=3):
    x = np.zeros((n, k))
    e = rng.standard_normal((n, k))
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    return x


def test_the_standard_error_covers_the_mean_of_white_and_of_correlated_samples():
    rng = np.random.default_rng(3)
    for phi in (0.0, 0.8):
        means, errors = [], []
        for _ in range(300):
            x = _ar1(rng, 400, phi)
            means.append(x.mean(axis=0))
            errors.append(standard_error_of_mean(x))
        spread = float(np.std(np.array(means)))  # the means' real scatter, per axis
        assert abs(np.mean(errors) / spread - 1.0) < 0.2, (phi, np.mean(errors), spread)
    # correlated samples are worth fewer: the AR(1) mean's scatter is ~3x a naive sigma / sqrt(n)
    x = _ar1(np.random.default_rng(4), 400, 0.8)
    assert standard_error_of_mean(x) > 2.0 * x.std(axis=0).mean() / np.sqrt(len(x))


def test_a_still_window_knows_the_gyro_bias_to_its_standard_error_not_its_spread():
    rng = np.random.default_rng(5)
    n = 100
    t = np.arange(n) * 5_000_000
    gyro = 0.002 + 1e-3 * rng.standard_normal((n, 3))
    accel = np.array([0.0, 0.0, 9.81]) + 0.01 * rng.standard_normal((n, 3))
    est = initialization.estimate([(t[i], *gyro[i], *accel[i]) for i in range(n)], TrackerOptions())
    assert est.still
    assert 0.7e-4 < est.gyro_mean_std < 1.4e-4  # 1e-3 / sqrt(100)
    assert abs(est.b_g - 0.002).max() < 4 * est.gyro_mean_std
