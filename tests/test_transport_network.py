"""The paper's network model and the device slowdown, as pure functions."""

import time

import pytest

from client_sdk import network_model as nm
from client_sdk.slowdown import PIXEL2_FACTOR, FrontendCosts, Slowdown


def test_paper_arithmetic_100kB_is_35_to_66_ms():
    opts = nm.NetworkOptions()  # 50 Mbps, 10 ms each way, U(0, 30) ms, fixed 100 kB
    assert nm.transmission_ns(100 * 1024, 50.0) == 15_625_000  # 100 * 8 / 1024 / 50 s
    rtts_ms = [nm.sample(opts, key, request_bytes=123).round_trip_ns / 1e6 for key in range(3000)]
    assert min(rtts_ms) >= 35.625 and max(rtts_ms) <= 65.625
    assert min(rtts_ms) < 36.0 and max(rtts_ms) > 65.0  # the whole range is used
    assert 49.0 < sum(rtts_ms) / len(rtts_ms) < 52.3  # mean 50.6 ms


def test_sample_is_a_pure_function_of_seed_and_key():
    a, b = nm.NetworkOptions(seed=1), nm.NetworkOptions(seed=2)
    assert nm.sample(a, 17, 0) == nm.sample(a, 17, 0)
    assert nm.sample(a, 17, 0) != nm.sample(a, 18, 0)
    assert nm.sample(a, 17, 0) != nm.sample(b, 17, 0)


def test_real_payload_size_and_downlink():
    opts = nm.NetworkOptions(fixed_payload_bytes=None, extra_max_ms=0.0, count_downlink_payload=True)
    d = nm.sample(opts, 0, request_bytes=2 * 102_400, response_bytes=0)
    assert d.uplink_ns == 2 * 15_625_000 + 10_000_000
    assert d.downlink_ns == 10_000_000
    assert nm.sample(opts, 0, 0, response_bytes=1024).downlink_ns > 10_000_000


def test_zero_network_and_bad_options():
    assert nm.sample(nm.NetworkOptions.zero(), 3, 10**6).round_trip_ns == 0
    with pytest.raises(ValueError, match="bandwidth"):
        nm.NetworkOptions(bandwidth_mbps=0)


def test_slowdown_models_in_replay_and_stretches_live():
    s = Slowdown(PIXEL2_FACTOR, FrontendCosts(pim_ns=100_000))
    assert abs(PIXEL2_FACTOR - 2.46) < 0.01
    assert s.virtual_ns("pim") == round(PIXEL2_FACTOR * 100_000)
    assert s.virtual_ns("ppm", count=10) == round(PIXEL2_FACTOR * s.costs.ppm_ns * 10)
    with pytest.raises(ValueError, match="unknown frontend operation"):
        s.virtual_ns("render")
    with pytest.raises(ValueError):
        Slowdown(0.5)
    start = time.perf_counter()
    with Slowdown(3.0).stretch():
        time.sleep(0.02)
    assert time.perf_counter() - start >= 0.055  # 0.02 of work + 2 * 0.02 of sleep
