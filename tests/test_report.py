"""`flextrack report`: the README's and docs' result sections are what the stored results give."""

import shutil
from pathlib import Path

import pytest

from flextrack import report
from flextrack.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_committed_pages_equal_what_flextrack_report_generates():
    stale = report.update(ROOT, check=True)
    assert not stale, f"run `flextrack report` and commit: {[str(p.relative_to(ROOT)) for p in stale]}"
    assert "<!-- results:table2 -->" in (ROOT / "README.md").read_text()


def test_every_stored_result_has_its_provenance_and_a_renderer():
    folders = [p for p in (ROOT / report.RESULTS_DIR).iterdir() if p.is_dir()]
    assert "table2" in {p.name for p in folders}
    for folder in folders:
        assert folder.name in report.RENDERERS, f"docs/results/{folder.name} has no @section renderer"
        own = folder / f"{folder.name}.json"
        runs = [own] if own.is_file() else sorted(folder.glob("*.json"))  # one run, or a folder of several
        assert runs, f"docs/results/{folder.name} has no provenance JSON"
        for path in runs:
            record = report.read_provenance(path)
            assert {"options", "commit", "dirty", "host", "date"} <= set(record), path.name
            assert len(record["commit"]) == 40, path.name


def _tree(tmp_path, page: str) -> Path:
    shutil.copytree(ROOT / report.RESULTS_DIR / "table2", tmp_path / report.RESULTS_DIR / "table2")
    (tmp_path / "README.md").write_text(page)
    return tmp_path


def test_a_hand_edited_cell_is_found_and_regenerated(tmp_path, capsys):
    generated = report.regenerate("intro\n<!-- results:table2 -->\n<!-- /results:table2 -->\nend\n", ROOT)
    assert generated.startswith("intro\n<!-- results:table2 -->\n") and generated.endswith("<!-- /results:table2 -->\nend\n")
    assert "| GT | 30 | 0.20 / " in generated and "Source: `flextrack experiment table2" in generated
    root = _tree(tmp_path, generated.replace("| GT | 30 | 0.20 / ", "| GT | 30 | 0.21 / "))
    assert main(["report", "--root", str(root), "--check"]) == 1
    assert "differs from its results" in capsys.readouterr().out
    assert main(["report", "--root", str(root)]) == 0
    assert (root / "README.md").read_text() == generated
    assert main(["report", "--root", str(root), "--check"]) == 0


def test_a_marker_without_results_is_refused(tmp_path, capsys):
    root = _tree(tmp_path, "<!-- results:nope -->\n<!-- /results:nope -->\n")
    assert main(["report", "--root", str(root)]) == 2
    assert "no renderer for results:nope" in capsys.readouterr().err
    with pytest.raises(FileNotFoundError):
        report.render("table2", tmp_path / "elsewhere")


def test_source_lines_name_the_seeds_a_rerun_needs():
    assert report.seed_flags([0]) == "" and report.seed_flags([]) == ""
    assert report.seed_flags([0, 1, 2]) == " --seeds 3"
    assert report.seed_flags([5]) == " --seed 5" and report.seed_flags([10, 11, 12]) == " --seed 10 --seeds 3"
