"""A run's NEES, whole and its rotation block's, and the interval of its mean that allows for correlated
frames (from the series' autocorrelation, or from the filter's error dynamics): right coverage on series
whose truth is known."""

import numpy as np
import pytest

from client_sdk.eskf.error_dynamics import ErrorDynamics
from flextrack.autocorrelation import autocorrelation_time
from flextrack.evaluation.consistency import model_nees_interval, nees_mean_interval
from flextrack.geometry import so3
from flextrack.geometry.camera import PinholeCamera
from flextrack.runners.results import TrackRecord


def test_a_record_scores_the_nees_and_its_rotation_block_on_the_wire_convention():
    truth = np.eye(4)
    truth[:3, 3] = (0.05, -0.02, 0.6)
    estimate = truth.copy()
    estimate[:3, :3] = so3.exp(-np.array([0.002, 0.0, 0.0])) @ truth[:3, :3]  # R_true = Exp(e_r) R_est
    estimate[:3, 3] -= (0.0, 0.003, 0.0)  # t_true = t_est + e_t
    covariance = np.diag([0.001**2] * 3 + [0.001**2] * 3)
    covariance[0, 3] = covariance[3, 0] = 0.5e-6  # a correlation: the rotation block alone differs from the whole
    record = TrackRecord(PinholeCamera(500.0, 500.0, 320.0, 240.0, 640, 480), np.zeros((1, 3)))
    record.add(0, 0, "FINE", estimate, truth, covariance)
    row = record.scored()[0]
    e = np.array([0.002, 0, 0, 0, 0.003, 0])
    assert row.nees == pytest.approx(e @ np.linalg.solve(covariance, e), rel=1e-6)
    assert row.nees_rotation == pytest.approx(4.0, rel=1e-6)  # (0.002 / 0.001)^2
    assert record.summarize().nees_rotation_mean == row.nees_rotation


def correlated_nees(rng, n, phi, scale=1.0):
    """NEES of a 6-dof error that follows an AR(1) process (consecutive frames share most of it)."""
    e = np.zeros((n, 6))
    e[0] = rng.standard_normal(6)
    for k in range(1, n):
        e[k] = phi * e[k - 1] + np.sqrt(1 - phi**2) * rng.standard_normal(6)
    return scale * (e**2).sum(axis=1)


def test_independent_frames_get_the_usual_interval():
    x = np.random.default_rng(0).chisquare(6, 4000)
    interval = nees_mean_interval(x)
    assert autocorrelation_time(x) < 1.2 and interval.n_eff > 3300
    assert interval.holds(x.mean()) and 5.8 < interval.lo < 6 < interval.hi < 6.2


def test_the_interval_covers_a_consistent_estimator_about_95_percent_of_the_time():
    rng = np.random.default_rng(1)
    runs = [correlated_nees(rng, 1500, 0.9) for _ in range(200)]
    covered = np.mean([nees_mean_interval(x).holds(x.mean()) for x in runs])
    naive = np.mean([abs(x.mean() - 6) < 1.96 * np.sqrt(12 / len(x)) for x in runs])  # as if independent
    assert 0.88 <= covered <= 0.99, covered
    assert naive < 0.6, naive  # the independent-frames interval would call most consistent runs inconsistent


def test_an_overconfident_estimator_fails():
    x = correlated_nees(np.random.default_rng(2), 3000, 0.9, scale=2.0)  # covariance half the truth
    interval = nees_mean_interval(x)
    assert not interval.holds(x.mean()) and x.mean() > interval.hi


def ar1_dynamics(n, phi):
    """The error dynamics of `correlated_nees`: one frame per anchor, e_t = phi e_(t-1) + noise, P = I."""
    dynamics = ErrorDynamics()
    dynamics.restart(np.eye(6))
    for t in range(n):
        if t:
            dynamics.link(phi * np.eye(6), np.eye(6))
        dynamics.frame(t, np.eye(6))
    return dynamics


def test_the_model_interval_is_the_one_the_error_dynamics_imply():
    n, phi = 400, 0.9
    interval = model_nees_interval([(t, np.eye(6)) for t in range(n)], ar1_dynamics(n, phi))
    lags = np.abs(np.subtract.outer(np.arange(n), np.arange(n)))
    assert interval.n_eff == pytest.approx(n * n / np.sum(phi ** (2 * lags)), rel=1e-6)
    independent = model_nees_interval([(t, np.eye(6)) for t in range(n)], ar1_dynamics(n, 0.0))
    assert independent.n_eff == pytest.approx(n)  # no link: the usual interval


def test_the_model_interval_covers_a_consistent_estimator_about_95_percent_of_the_time():
    """Runs as long as the errors' correlation (here 0.995 per frame): the series' own autocorrelation cannot
    see it and its interval is far too narrow, the model's is right."""
    rng = np.random.default_rng(3)
    n, phi = 600, 0.995
    interval = model_nees_interval([(t, np.eye(6)) for t in range(n)], ar1_dynamics(n, phi))
    runs = [correlated_nees(rng, n, phi) for _ in range(300)]
    covered = np.mean([interval.holds(x.mean()) for x in runs])
    from_series = np.mean([nees_mean_interval(x).holds(x.mean()) for x in runs])
    assert 0.9 <= covered <= 0.99, covered
    assert from_series < 0.8, from_series
