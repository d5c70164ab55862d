"""`flextrack bench capacity --cpu-cost DEVICES`: a fixed offered load on real `flextrack serve` and echo
processes, the server's CPU a frame from /proc and the devices per core derived from it (no timing asserted)."""

import json

from flextrack.cli import main


def test_cpu_cost_measures_each_backend_at_a_fixed_load_and_stores_it(tmp_path, capsys):
    rc = main(["bench", "capacity", "--cpu-cost", "2", "--step-s", "1", "--repeats", "1", "--payload-kb", "5",
               "--out", str(tmp_path)])
    assert rc == 0
    data = json.loads((tmp_path / "capacity.json").read_text())
    cost = data["cpu_cost"]
    assert cost["devices"] == 2 and set(cost["backends"]) == {"echo", "gt_oracle"}
    for entry in cost["backends"].values():
        assert entry["answered"] > 0 and entry["offered_fps"] == 60
        assert entry["gross_cpu_ms_per_frame"] >= entry["cpu_ms_per_frame"] >= 0
        assert entry["devices_per_core"] > 0 and entry["latency_ms"]["p99_ms"] > 0
    assert cost["backends"]["gt_oracle"]["exit_code"] == 0  # a graceful stop (the echo has none)
    assert data["provenance"]["options"]["cpu_cost"] == 2 and "commit" in data["provenance"]
    assert "devices/core" in capsys.readouterr().out


def test_cpu_cost_needs_a_device(tmp_path, capsys):
    assert main(["bench", "capacity", "--cpu-cost", "0", "--out", str(tmp_path)]) == 2
    assert "--cpu-cost must be at least 1" in capsys.readouterr().err
