"""The README's demo table is generated from the stored demo result (docs/results/demo/), and its replay rows
are what `flextrack demo` prints today: the replays run in virtual time, so they are the same on every run,
and a change of the tracker, the network model or the simulator that moves them fails here until the demo
is rerun and stored (`flextrack demo --out out/demo`, copy demo.json to docs/results/demo/, `flextrack report`)."""

from __future__ import annotations

import json
import re
from pathlib import Path

from flextrack.cli import command_parser
from flextrack.formats import sequence as sequence_io
from flextrack.runners import demo
from flextrack.runners.results import format_table

ROOT = Path(__file__).resolve().parents[1]
STORED = ROOT / "docs" / "results" / "demo" / "demo.json"


def section_rows(page: Path, name: str = "demo") -> dict[str, str]:
    """The table rows between a page's results markers, by run name."""
    text = page.read_text()
    body = re.search(rf"<!-- results:{name} -->\n(.*?)<!-- /results:{name} -->", text, re.DOTALL).group(1)
    return {line.split("|")[1].strip(): line for line in body.splitlines() if line.startswith("| ") and
            not line.startswith("| run ")}


def test_the_readme_demo_rows_are_the_stored_result_and_the_replay_rows_what_the_demo_prints(tmp_path):
    stored = json.loads(STORED.read_text())
    options = {k: v for k, v in stored["provenance"]["options"].items() if k != "command"}
    args = command_parser("demo", demo).parse_args(["--out", str(tmp_path)])
    assert {k: v for k, v in vars(args).items() if k != "out"} == {k: v for k, v in options.items() if k != "out"}, \
        "the stored demo ran with other options than `flextrack demo`'s defaults: rerun it"
    seq = sequence_io.load(demo.simulate(tmp_path, args))
    from client_sdk.network_model import NetworkOptions
    from client_sdk.options import preset

    runs = demo.replay_runs(seq, preset(args.tracker), NetworkOptions(seed=args.seed), demo.default_registry(seq))
    printed = format_table([(name, record.summarize()) for name, record in runs]).splitlines()[2:]
    readme = section_rows(ROOT / "README.md")
    assert set(readme) == {r["run"] for r in stored["runs"]} and len(printed) == 2
    for line in printed:
        name = line.split("|")[1].strip()
        assert readme[name] == line, (f"README's '{name}' row differs from what `flextrack demo` prints now; rerun "
                                      "the demo, store its demo.json in docs/results/demo/ and run `flextrack report`")
