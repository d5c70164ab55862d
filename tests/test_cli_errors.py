"""Every command fails on a bad argument, path, port, config or unreachable server with one line on stderr
that says what is wrong and what to do, a non-zero exit and no traceback (issue 19, points 10-14); and
`flextrack loadtest` against the default server config gets OK answers out of the box."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time

import pytest

from flextrack.cli import main
from flextrack.testing.toy_sequence import write_orbit_sequence


def one_line(capsys) -> str:
    """The command's stderr: exactly one line, no traceback."""
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err and len(err.splitlines()) == 1, err
    return err


def free_port() -> int:
    """A loopback port where nothing listens."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def seq(tmp_path_factory):
    return write_orbit_sequence(tmp_path_factory.mktemp("seq") / "orbit", frames=30)


@pytest.fixture(scope="module")
def default_server():
    from estimators.registry import EstimatorRegistry
    from flextrack.assets import default_config_path
    from service.server import BackgroundServer

    with BackgroundServer(EstimatorRegistry.from_config(default_config_path()), grace_s=0.0) as srv:
        yield srv


def test_loadtest_against_the_default_server_gets_ok_answers(default_server, tmp_path, capsys):
    rc = main(["loadtest", "--target", default_server.address, "--clients", "2", "--answers", "4", "--duration", "120",
               "--warmup", "0", "--payload-kb", "5", "--out", str(tmp_path)])
    assert rc == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "load_summary.json").read_text())
    assert set(summary["outcomes"]) == {"OK"} and summary["answered"] == 8


def test_loadtest_with_mostly_error_answers_exits_non_zero_saying_why(default_server, tmp_path, capsys):
    rc = main(["loadtest", "--target", default_server.address, "--clients", "1", "--answers", "3", "--duration", "120",
               "--warmup", "0", "--payload-kb", "5", "--estimator", "gt_oracle", "--out", str(tmp_path)])
    assert rc == 1
    err = one_line(capsys)
    assert "status:INVALID_INPUT" in err and "sequence_roots" in err


@pytest.mark.parametrize("target", ["localhost", "foo:bar", "127.0.0.1:70000"])
def test_loadtest_malformed_target(target, tmp_path, capsys):
    assert main(["loadtest", "--target", target, "--out", str(tmp_path)]) == 2
    assert "expected HOST:PORT" in one_line(capsys)


def test_loadtest_where_nothing_listens(tmp_path, capsys):
    assert main(["loadtest", "--target", f"127.0.0.1:{free_port()}", "--duration", "0.5", "--out", str(tmp_path)]) == 1
    assert "nothing answered" in one_line(capsys)


def test_track_against_a_server_where_nothing_listens_fails_fast(seq, tmp_path, capsys):
    start = time.perf_counter()
    rc = main(["track", str(seq.root), "--server", f"127.0.0.1:{free_port()}", "--out", str(tmp_path / "o")])
    assert rc == 1 and time.perf_counter() - start < 10
    err = one_line(capsys)
    assert "nothing answered" in err and "flextrack serve" in err


@pytest.mark.parametrize("backend, reason", [
    ("gt", "unknown estimator 'gt'; available: ['gt_oracle', 'gt_noisy'"),
    ("gt_oracle", "estimator 'gt_oracle' has no sequence 'orbit'"),
])
def test_track_names_the_servers_reason_when_it_refuses_the_first_request(default_server, seq, tmp_path, backend,
                                                                          reason, capsys):
    """The first request goes out before anything is tracked or rendered; a refusal stops the run with the
    server's own status and message, not a guess."""
    rc = main(["track", str(seq.root), "--server", default_server.address, "--backend", backend, "--no-plots",
               "--out", str(tmp_path / "o")])
    err = one_line(capsys)
    assert rc == 1 and f"the server at {default_server.address} refused the first request: INVALID_INPUT: " in err
    assert reason in err and not (tmp_path / "o").exists()


@pytest.mark.parametrize("server", [False, True])
@pytest.mark.parametrize("backend, reason", [("pnp", "keypoints"), ("region", "cannot give the first pose")])
def test_track_refuses_up_front_a_backend_that_cannot_work_from_track(default_server, seq, tmp_path, server, backend,
                                                                      reason, capsys):
    where = ["--server", default_server.address] if server else []
    rc = main(["track", str(seq.root), *where, "--backend", backend, "--out", str(tmp_path / "o")])
    err = one_line(capsys)
    assert rc == 2 and err.startswith(f"flextrack track: --backend {backend}: ") and reason in err


def test_track_non_oracle_backend_uses_the_default_config(seq, tmp_path, capsys):
    # an estimator no config has: the names listed are the default config's (pvnet among them), and --config is named
    rc = main(["track", str(seq.root), "--backend", "nosuch", "--no-plots", "--out", str(tmp_path / "o")])
    assert rc == 2
    err = one_line(capsys)
    assert "'pvnet'" in err and "--config" in err


def test_track_folder_that_is_not_a_sequence(tmp_path, capsys):
    assert main(["track", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "not a sequence folder (no rig.yaml)" in one_line(capsys)


def test_track_corrupt_rig_yaml(seq, tmp_path, capsys):
    import shutil

    root = tmp_path / "broken"
    shutil.copytree(seq.root, root)
    (root / "rig.yaml").write_text("T_BC: [1, 2\n  width: : :\n")
    assert main(["track", str(root), "--out", str(tmp_path / "o")]) == 2
    assert "rig.yaml: not valid YAML" in one_line(capsys)


@pytest.mark.parametrize("command", ["track", "simulate"])
def test_out_naming_an_existing_file_is_refused_before_any_work(command, seq, tmp_path, capsys):
    existing = tmp_path / "file.txt"
    existing.write_text("x")
    argv = ["track", str(seq.root)] if command == "track" else ["simulate", "--duration", "1"]
    start = time.perf_counter()
    assert main([*argv, "--out", str(existing)]) == 2
    assert time.perf_counter() - start < 5
    assert "is an existing file" in one_line(capsys)


def test_track_speed_without_live_is_refused(seq, tmp_path, capsys):
    assert main(["track", str(seq.root), "--speed", "4", "--out", str(tmp_path / "o")]) == 2
    assert "--live" in one_line(capsys)


def test_serve_negative_port_is_refused(capsys):
    assert main(["serve", "--port", "-3"]) == 2
    assert "--port" in one_line(capsys)


@pytest.mark.parametrize("argv, says", [
    (["serve", "--workers", "0"], "--workers must be >= 1"),
    (["serve", "--grace-s", "-1"], "--grace-s >= 0"),
    (["evaluate", "prior", "--bop", "/nonexistent", "--obj-id", "6"], "no BOP split folder"),
    (["bench", "tracker", "--fps", "0"], "must be > 0"),
    (["report", "--check", "--root", "/nonexistent"], "holds no docs/results/"),
    (["simulate", "--fps", "0", "--out", "/nonexistent/x"], "--fps must be a number in (0, 1000]"),
    (["loadtest", "--target", "127.0.0.1:1", "--clients", "0", "--out", "/nonexistent/x"],
     "--clients must be a number in [1, 100000]"),
])
def test_bad_values_are_one_line_and_exit_2(argv, says, capsys):
    assert main(argv) == 2
    assert says in one_line(capsys)


def test_demo_refuses_a_file_for_its_out_folder_before_any_work(tmp_path, capsys):
    afile = tmp_path / "a_file"
    afile.write_text("x")
    assert main(["demo", "--out", str(afile)]) == 2
    assert "is an existing file" in one_line(capsys)


def test_track_set_names_the_unknown_option_and_a_close_one(seq, tmp_path, capsys):
    assert main(["track", str(seq.root), "--set", "px_eror=3", "--out", str(tmp_path / "o")]) == 2
    assert "unknown option 'px_eror'; did you mean px_error?" in one_line(capsys)


def test_flextrack_alone_prints_help_and_exits_2():
    done = subprocess.run([sys.executable, "-m", "flextrack"], check=False, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "usage: flextrack" in done.stderr and "Traceback" not in done.stderr


@pytest.mark.parametrize("argv, says", [(["table2", "--fps", "45"], "choose among"),
                                        (["table2", "--set", "px_error=15"], "apply to euroc"),
                                        (["euroc", "--fps", "30", "60"], "one frame rate"),
                                        (["filter", "--seeds", "0"], "--seeds must be at least 1"),
                                        (["filter", "--data", "/tmp"], "--data applies to euroc"),
                                        (["ablation", "--backend", "pvnet"], "--backend applies to table2"),
                                        (["table2", "--backend", "region"], "chained estimator")])
def test_experiment_options_that_cannot_apply_are_refused(argv, says, tmp_path, capsys):
    assert main(["experiment", *argv, "--out", str(tmp_path)]) == 2
    assert says in one_line(capsys)


def test_experiment_euroc_bad_set_is_one_line(tmp_path, capsys):
    assert main(["experiment", "euroc", "--set", "nonsense=1", "--out", str(tmp_path)]) == 2
    assert "--set 'nonsense=1'" in one_line(capsys)


def test_track_bad_fps_and_missing_config(seq, tmp_path, capsys):
    assert main(["track", str(seq.root), "--fps", "0", "--out", str(tmp_path / "o")]) == 2
    assert "--fps must be a number in (0, 1000], got 0" in one_line(capsys)
    assert main(["track", str(seq.root), "--config", str(tmp_path / "nope.toml"), "--out", str(tmp_path / "o")]) == 2
    assert "no such file" in one_line(capsys)


def test_serve_config_that_is_not_toml(tmp_path, capsys):
    bad = tmp_path / "bad.toml"
    bad.write_text("not [valid toml\n")
    assert main(["serve", "--config", str(bad), "--port", "0"]) == 2
    assert "not valid TOML" in one_line(capsys)


@pytest.mark.parametrize("argv", [
    ["simulate", "--duration", "inf"], ["simulate", "--imu-jitter", "-1"], ["simulate", "--fps", "100000"],
    ["track", "SEQ", "--slowdown", "inf"], ["track", "SEQ", "--backend-ms", "-1000"],
    ["experiment", "table2", "--duration", "inf"], ["experiment", "euroc", "--fps", "inf"],
    ["experiment", "euroc", "--fps", "0"], ["loadtest", "--target", "127.0.0.1:1", "--payload-kb", "-5"],
    ["convert-euroc", "--fps", "nan"], ["convert-euroc", "--frame-latency", "-5"],
    ["evaluate", "nees", "--pnp-noise-px", "inf"],
])
def test_bad_numbers_get_one_line_and_exit_2(argv, seq, tmp_path, capsys):
    """Issue 31 item 7: inf, nan, negative sizes and rates no machine keeps up with, refused before any work."""
    argv = [str(seq.root) if a == "SEQ" else a for a in argv] + ["--out", str(tmp_path / "o")]
    assert main(argv) == 2
    option = next(a for a in argv if a.startswith("--") and a != "--target")
    assert f"{option} must be a number in " in one_line(capsys)
    assert not (tmp_path / "o").exists()


def test_evaluate_nees_out_naming_a_file_is_refused(tmp_path, capsys):
    (tmp_path / "f").write_text("")
    assert main(["evaluate", "nees", "--out", str(tmp_path / "f")]) == 2
    assert "is an existing file" in one_line(capsys)


def test_evaluate_nees_says_why_it_exits_1_and_help_says_what_each_exit_means(tmp_path, capsys):
    rc = main(["evaluate", "nees", "--estimators", "pnp", "--pnp-answers", "60", "--pnp-tune-answers", "20",
               "--pnp-noise-px", "3", "--out", str(tmp_path)])
    err = one_line(capsys)
    assert rc == 1 and err.startswith("flextrack evaluate nees: not calibrated: pnp mean NEES ")
    assert "(errors larger than its covariance says)" in err
    with pytest.raises(SystemExit):
        main(["evaluate", "nees", "--help"])
    shown = capsys.readouterr().out.replace("\n", " ")
    assert "Exit status: 0 when" in shown and "examples:" in shown


def test_convert_euroc_default_input_works_from_outside_the_checkout(tmp_path, monkeypatch, capsys):
    from flextrack.experiments.euroc import DEFAULT_DATA

    if not DEFAULT_DATA.is_dir():
        pytest.skip(f"no shared EuRoC data at {DEFAULT_DATA}")
    monkeypatch.chdir(tmp_path)
    assert main(["convert-euroc", "--no-plots", "--out", "seq"]) == 0
    assert (tmp_path / "seq" / "rig.yaml").is_file() and "wrote seq" in capsys.readouterr().out


def test_convert_euroc_missing_folder_is_reported_as_missing(tmp_path, capsys):
    assert main(["convert-euroc", "--euroc", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert f"--euroc {tmp_path / 'nope'}: no such folder" in one_line(capsys)


def test_a_missing_extra_is_named_as_a_wheel_user_installs_it():
    from flextrack.cli import extra_for

    assert [extra_for(m) for m in ("pyrender", "matplotlib.pyplot", "torch", "onnxruntime", None)] == \
        ["sim", "sim", "train", "server", "server"]
