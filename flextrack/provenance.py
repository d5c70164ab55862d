"""Where a result came from: the options, the commit (and whether the tree was dirty), the host and the date.

Every result file the experiments, benchmarks and `track` write carries this record, so that a table
can always be traced to the run that made it.
"""

from __future__ import annotations

import datetime
import json
import platform
import subprocess
import sys
from pathlib import Path

_HERE = Path(__file__).resolve().parent


def _git(*args: str) -> str:
    try:
        done = subprocess.run(["git", *args], cwd=_HERE, capture_output=True, text=True, check=False, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return done.stdout.strip() if done.returncode == 0 else ""


_SECRET = ("metadata", "credentials", "token", "password")  # never written: may hold a bearer token


def provenance(**options) -> dict:
    """The record: `options` as given (seeds included; made JSON-safe: paths and other objects as text,
    credentials and metadata left out), commit, dirty, host, python and the UTC date."""
    options = json.loads(json.dumps({k: v for k, v in options.items() if k not in _SECRET}, default=str))
    commit = _git("rev-parse", "HEAD") or None
    return {"options": options, "commit": commit,
            "dirty": bool(_git("status", "--porcelain", "--untracked-files=no")) if commit else None,
            "host": platform.node(), "python": platform.python_version(),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}


def command_line(*words: str) -> str:
    """The command as typed, `flextrack WORDS ARGS...`: the arguments after WORDS when sys.argv holds them, else
    all of sys.argv's (a module run on its own)."""
    n = len(words)
    rest = sys.argv[1 + n:] if sys.argv[1:1 + n] == list(words) else sys.argv[1:]
    return " ".join(["flextrack", *words, *rest])


def of_args(args, **extra) -> dict:
    """The record of a command: its parsed arguments (an argparse Namespace) and `extra` as the options."""
    return provenance(**vars(args), **extra)
