"""flextrack.provenance: the record every result file carries."""

import argparse
import json
from pathlib import Path

from flextrack.provenance import of_args, provenance


def test_the_record_is_json_safe_names_the_commit_and_never_holds_credentials():
    record = provenance(out=Path("out/x"), seeds=[0, 1], credentials=object(), metadata=(("authorization", "Bearer s"),),
                        token="s", rate=float("nan"))
    text = json.dumps(record)  # JSON-safe: paths and objects as text
    assert record["options"]["out"] == "out/x" and record["options"]["seeds"] == [0, 1]
    assert "Bearer" not in text and not {"credentials", "metadata", "token"} & set(record["options"])
    assert len(record["commit"]) == 40 and isinstance(record["dirty"], bool)  # this checkout is a git tree
    assert record["host"] and record["python"] and record["date"].endswith("+00:00")


def test_of_args_records_a_commands_arguments():
    args = argparse.Namespace(out=Path("o"), seed=3, token_file=Path("tokens"))
    options = of_args(args, command="flextrack x")["options"]
    assert options == {"out": "o", "seed": 3, "token_file": "tokens", "command": "flextrack x"}
