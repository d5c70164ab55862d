"""`flextrack loadtest` against real loopback servers: figures, files, ramp, and round_robin spread."""

from __future__ import annotations

import csv
import json
import time

import pytest

from estimators.base import EstimateInput, EstimateOutput, Estimator
from estimators.gt_oracle import GtOracleEstimator
from estimators.registry import EstimatorRegistry
from flextrack.cli import main
from flextrack.loadtest import front_proxy, runner, workload
from flextrack.testing.toy_sequence import write_orbit_sequence
from service.hardening import Hardening
from service.server import BackgroundServer


@pytest.fixture(scope="module")
def oracle(tmp_path_factory):
    seq = write_orbit_sequence(tmp_path_factory.mktemp("seq") / "orbit", frames=30)
    return EstimatorRegistry([GtOracleEstimator("gt_oracle", [seq.root])]), seq


def test_loadtest_cli_reports_and_writes_csv_and_plot(oracle, tmp_path, capsys):
    registry, seq = oracle
    with BackgroundServer(registry, grace_s=0.0) as srv:
        rc = main(["loadtest", "--target", srv.address, "--clients", "3", "--fps", "30", "--payload-kb", "20",
                   "--estimator", "gt_oracle", "--sequence", str(seq.root), "--duration", "1", "--warmup", "0.3",
                   "--out", str(tmp_path)])
    assert rc == 0
    printed = capsys.readouterr().out
    assert "p50/p95/p99" in printed and "outcomes OK=" in printed
    summary = json.loads((tmp_path / "load_summary.json").read_text())
    assert summary["outcomes"].keys() == {"OK"} and summary["answered"] > 30
    prov = summary["provenance"]  # the load spec (seed included), commit, dirty, host, date; never the credentials
    assert prov["options"]["clients"] == 3 and "seed" in prov["options"] and "credentials" not in prov["options"]
    assert {"commit", "dirty", "host", "date"} <= set(prov)
    with open(tmp_path / "load_requests.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == summary["answered"] and {r["client"] for r in rows} == {"0", "1", "2"}
    assert (tmp_path / "load_latency.png").stat().st_size > 10_000


def test_ramp_finds_the_largest_passing_client_count(oracle, tmp_path, capsys):
    """Each step ends on an event (every client has 4 answers), not a time window: a busy machine gives
    fewer answers a second, never an empty step. --duration only bounds a step."""
    registry, seq = oracle
    with BackgroundServer(registry, grace_s=0.0) as srv:
        rc = main(["loadtest", "--target", srv.address, "--ramp", "--clients", "1", "--max-clients", "4", "--fps", "20",
                   "--payload-kb", "5", "--sequence", str(seq.root), "--answers", "4", "--duration", "120",
                   "--warmup", "0", "--p99-bound-ms", "4000", "--out", str(tmp_path)])
    assert rc == 0
    ramp = json.loads((tmp_path / "ramp.json").read_text())
    assert ramp["best_clients"] == 4 and [s["clients"] for s in ramp["steps"]] == [1, 2, 4]
    assert [s["answered"] for s in ramp["steps"]] == [4, 8, 16]
    assert (tmp_path / "ramp.png").exists() and "largest client count" in capsys.readouterr().out


def test_ramp_where_every_answer_fails_exits_non_zero_with_the_reason(oracle, tmp_path, capsys):
    registry, seq = oracle
    with BackgroundServer(registry, grace_s=0.0) as srv:
        rc = main(["loadtest", "--target", srv.address, "--ramp", "--clients", "1", "--fps", "20", "--payload-kb", "5",
                   "--estimator", "no_such_estimator", "--sequence", str(seq.root), "--answers", "3",
                   "--duration", "120", "--warmup", "0", "--out", str(tmp_path)])
    out, err = capsys.readouterr()
    assert rc == 1 and "errors 100.0% of 3 answers -> fail" in out
    assert any(line.startswith("flextrack loadtest: no client count passed: 1 clients: 100% of 3 answers were errors")
               for line in err.splitlines()), err
    assert "no_such_estimator" in err and len(err.strip().splitlines()) == 1


class _Slow(Estimator):
    """Answers after a second: longer than the whole measured window below, however fast the machine."""

    kind, version = "slow", "1"

    def __init__(self):
        super().__init__("slow", ["obj"])

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        time.sleep(1.0)
        return EstimateOutput.not_found("slow")


def test_a_ramp_step_with_no_answers_is_reported_as_such(tmp_path, capsys):
    """The first request (sent in the warm-up) is answered after the window ended: the step got no answer,
    which is said so (not as 'errors 100 %'), with no error rate in ramp.csv, and the ramp exits 1."""
    with BackgroundServer(EstimatorRegistry([_Slow()]), grace_s=0.0) as srv:
        rc = main(["loadtest", "--target", srv.address, "--ramp", "--clients", "1", "--max-clients", "1",
                   "--fps", "20", "--payload-kb", "5", "--estimator", "slow", "--warmup", "0.2", "--duration", "0.1",
                   "--out", str(tmp_path)])
    out, err = capsys.readouterr()
    assert rc == 1 and "   1 clients: no answers in " in out and "errors" not in out
    assert err.startswith("flextrack loadtest: no client count passed: 1 clients: nothing answered at ")
    with open(tmp_path / "ramp.csv") as f:
        (row,) = list(csv.DictReader(f))
    assert row["answered"] == "0" and row["error_rate"] == "" and row["passed"] == "False"


def test_round_robin_over_two_addresses_spreads_the_streams(oracle):
    registry, seq = oracle
    hardening = [Hardening(), Hardening()]
    with BackgroundServer(registry, grace_s=0.0, hardening=hardening[0]) as a, \
            BackgroundServer(registry, grace_s=0.0, hardening=hardening[1]) as b:
        spec = runner.LoadSpec((a.address, b.address), clients=4, fps=30, duration_s=120, warmup_s=0, answers=3)
        result = runner.run(spec, workload.from_sequence(seq.root, payload_kb=5))
    assert len(result.samples) == 12
    served = [h.metrics.count("OK", "Track") for h in hardening]
    assert all(n > 0 for n in served)  # both replicas got streams
    assert sum(served) >= len(result.samples)


def test_bad_targets_and_options_are_refused_clearly(tmp_path, capsys):
    assert main(["loadtest", "--target", "a.example:1,b.example:2", "--out", str(tmp_path)]) == 2
    assert "IPv4 host:port" in capsys.readouterr().err
    assert main(["loadtest", "--target", "127.0.0.1:1", "--clients", "0", "--out", str(tmp_path)]) == 2
    assert runner.grpc_target(["127.0.0.1:5", "127.0.0.1:6"]) == "ipv4:127.0.0.1:5,127.0.0.1:6"


@pytest.mark.parametrize("front", ["none", "nginx"])
def test_bench_capacity_overload_run_at_a_given_capacity(front, tmp_path, capsys):
    """The overload half of `flextrack bench capacity` on a real `flextrack serve` process: twice the given
    capacity, the excess refused with RESOURCE_EXHAUSTED (and a lone probe's refusals timed), the server up;
    by the server itself or by an nginx gate in front of it."""
    if front == "nginx" and front_proxy.nginx_binary() is None:
        pytest.skip("nginx is not installed (Debian: apt-get install nginx-light)")
    rc = main(["bench", "capacity", "--capacity", "4", "--step-s", "1.5", "--payload-kb", "10", "--front", front,
               "--out", str(tmp_path)])
    assert rc == 0
    overload = json.loads((tmp_path / "capacity.json").read_text())["backends"]["gt_oracle"]["overload"]
    assert overload["clients"] == 8 and overload["max_streams"] == 2 and overload["server_up_after"]
    assert overload["front"] == front and overload["exit_code"] == 0
    assert overload["outcomes"]["OK"] > 0 and overload["outcomes"]["grpc:RESOURCE_EXHAUSTED"] > 0
    assert overload["probe_refused_ms"]["p50_ms"] > 0  # the probe (every 0.1 s, ignoring pushback) was refused
    assert "capacity given: no ramps" in capsys.readouterr().out
