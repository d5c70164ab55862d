"""The rules of the house are import contracts (pyproject.toml's [tool.importlinter], run by `make lint`).

They hold for the tree as it is, and each one breaks when a forbidden import is added: the packages are
copied to a temporary folder, one import is added there, and lint-imports runs on the copy (first on
PYTHONPATH, so that the copy, not the checkout, is what it analyses).
"""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("client_sdk", "service", "estimators", "flextrack")
LIGHT = "client_sdk imports numpy, grpcio and protobuf and nothing heavier, and nothing of service or estimators"
NO_SERVICE = "estimators never import service (an estimator works in-process without a server)"
PURE_CORE = "the tracker core imports no clock, thread or socket module (those live in the shells)"
NO_SHELLS = "the tracker core does not import its shells (transport, interceptor, credentials, slowdown)"


def lint_imports(root: Path) -> tuple[int, str]:
    binary = Path(sys.executable).parent / "lint-imports"
    if not binary.exists():
        pytest.skip("lint-imports is not installed: pip install import-linter (part of the dev extra)")
    env = {**os.environ, "PYTHONPATH": str(root)}
    done = subprocess.run([str(binary), "--no-cache"], cwd=root, env=env,  # root's pyproject.toml
                          capture_output=True, text=True, timeout=120, check=False)
    return done.returncode, done.stdout + done.stderr


def reports(out: str, name: str, verdict: str) -> bool:
    """Whether the report says `name VERDICT` (it wraps long names at any space, or none, before the verdict)."""
    return "".join(f"{name}{verdict}".split()) in "".join(out.split())


@pytest.fixture
def tree(tmp_path) -> Path:
    """The four packages' Python files and pyproject.toml, copied."""
    for package in PACKAGES:
        shutil.copytree(REPO / package, tmp_path / package,
                        ignore=lambda d, names: [n for n in names if not (n.endswith(".py") or (Path(d) / n).is_dir())
                                                 or n == "__pycache__"])
    shutil.copy2(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def test_the_contracts_hold(tree):
    rc, out = lint_imports(tree)
    assert rc == 0, out
    for name in (LIGHT, NO_SERVICE, PURE_CORE, NO_SHELLS):
        assert reports(out, name, "KEPT"), out


@pytest.mark.parametrize(("module", "line", "contract"), [
    ("client_sdk/tracker.py", "import service", LIGHT),
    ("client_sdk/inspection.py", "import scipy", LIGHT),
    ("client_sdk/state.py", "from flextrack.simulator import imu", LIGHT),
    ("estimators/pnp.py", "from service import server", NO_SERVICE),
    ("client_sdk/propagation.py", "import time", PURE_CORE),
    ("client_sdk/refinement.py", "import threading", PURE_CORE),
    ("client_sdk/tracker.py", "from client_sdk import transport", NO_SHELLS),
], ids=["sdk-service", "sdk-scipy", "sdk-simulator", "estimators-service", "core-time", "core-threading",
        "core-transport"])
def test_a_forbidden_import_breaks_its_contract(tree, module, line, contract):
    path = tree / module
    path.write_text(path.read_text() + f"\n{line}  # added by the test\n")
    rc, out = lint_imports(tree)
    assert rc != 0, out
    assert reports(out, contract, "BROKEN"), out
