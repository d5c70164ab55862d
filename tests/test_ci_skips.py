"""Under CI=true a skip fails (tests/conftest.py), unless the data under ../shared is absent."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

SAMPLE = '''
import pytest

def test_needs_a_tool():
    pytest.skip("nginx is not installed")

def test_needs_shared_data():
    pytest.skip("/x/shared/data/euroc absent (shared data not mounted)")

@pytest.mark.xfail(reason="known")
def test_known_failure():
    assert False
'''


def _pytest(tmp_path: Path, ci: str) -> subprocess.CompletedProcess:
    shutil.copy(Path(__file__).with_name("conftest.py"), tmp_path / "conftest.py")
    (tmp_path / "test_sample.py").write_text(SAMPLE)
    env = dict(os.environ, CI=ci)
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                           str(tmp_path)], check=False, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)


def test_a_skip_fails_in_ci_unless_shared_data_is_absent(tmp_path):
    done = _pytest(tmp_path, "true")
    assert done.returncode == 1, done.stdout
    assert "1 failed, 1 skipped, 1 xfailed" in done.stdout
    assert "FAILED test_sample.py::test_needs_a_tool - skipped under CI=true" in done.stdout


def test_outside_ci_a_skip_stays_a_skip(tmp_path):
    done = _pytest(tmp_path, "")
    assert done.returncode == 0, done.stdout
    assert "2 skipped, 1 xfailed" in done.stdout
