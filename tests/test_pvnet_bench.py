"""`flextrack bench pvnet --out`: the estimator as served and the float baseline on the same rendered frames,
whole and cropped, stored with their provenance (figures are printed and stored, never asserted)."""

import json

import pytest

pytest.importorskip("onnxruntime")
pytest.importorskip("pyrender")

from flextrack.cli import main


def test_bench_pvnet_stores_both_estimators_figures_whole_and_cropped(tmp_path, capsys):
    out = tmp_path / "bench_pvnet.json"
    assert main(["bench", "pvnet", "--frames", "2", "--batches", "", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    for part in ("whole", "crops"):
        models = data[part]["models"]
        assert list(models) == ["searches on pvnet_int8.onnx", "float throughout (baseline)"]
        for m in models.values():
            assert set(m["stage_ms"]) == {"decode", "inference", "voting", "pnp", "refine"}
            assert m["sum_ms"] > 0 and m["cpu_ms"] > 0 and 0 <= m["found"] <= 2
        assert data[part]["cpu_ratio"] > 0 and data[part]["frames"] == 2
    assert data["provenance"]["options"]["command"] == "flextrack bench pvnet"
    printed = capsys.readouterr().out
    assert "sum " in printed and "batch 1, crops as the SDK sends them" in printed


def test_bench_pvnet_refuses_a_missing_search_model(capsys):
    assert main(["bench", "pvnet", "--frames", "1", "--search-model", "/nonexistent.onnx"]) == 2
    assert "search_model" in capsys.readouterr().err
