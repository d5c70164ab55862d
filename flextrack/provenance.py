"""Where a result came from: the options, the commit (and whether the tree was dirty), the host and the date.

Every result file the experiments, benchmarks and `track` write carries this record, so that a table
can always be traced to the run that made it.
"""

from __future__ import annotations

import datetime
import platform
import subprocess
from pathlib import Path

_HERE = Path(__file__).resolve().parent


def _git(*args: str) -> str:
    try:
        done = subprocess.run(["git", *args], cwd=_HERE, capture_output=True, text=True, check=False, timeout=10)
    except (OSError, subprocess.TimeoutExpired):
        return ""
    return done.stdout.strip() if done.returncode == 0 else ""


def provenance(**options) -> dict:
    """The record: `options` as given (seeds included), commit, dirty, host, python and the UTC date."""
    commit = _git("rev-parse", "HEAD") or None
    return {"options": options, "commit": commit,
            "dirty": bool(_git("status", "--porcelain", "--untracked-files=no")) if commit else None,
            "host": platform.node(), "python": platform.python_version(),
            "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")}
