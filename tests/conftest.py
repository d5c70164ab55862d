"""In CI (environment CI=true) a skipped test is a failure, unless it skips because the data under
../shared is absent (real recordings that a clone does not carry). What a test needs beyond that
(nginx, hadolint, the dev extra) is installed by `make test`, so a skip there means CI did not run it.
Each test leaves the root logger's handlers as it found them: a test that runs `serve` in-process installs
the service's JSON handler, whose lines would otherwise land in later tests' captured stderr.
"""

from __future__ import annotations

import logging
import os
import re

import pytest

ALLOWED_IN_CI = re.compile(r"shared[/ ]data")  # the reason names ../shared/data or "the shared data folder"


@pytest.fixture(autouse=True)
def _root_log_handlers_restored():
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


def _in_ci() -> bool:
    return os.environ.get("CI", "").lower() == "true"


def _reason(report) -> str:
    longrepr = report.longrepr
    if isinstance(longrepr, tuple) and len(longrepr) == 3:
        return str(longrepr[2])
    return str(longrepr)


def _fail_if_skipped_in_ci(report) -> None:
    if not (_in_ci() and report.skipped and not hasattr(report, "wasxfail")):
        return
    reason = _reason(report)
    if ALLOWED_IN_CI.search(reason):
        return
    report.outcome = "failed"
    report.longrepr = (f"skipped under CI=true, which counts as a failure (only data under ../shared may be "
                       f"absent): {reason}")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    _fail_if_skipped_in_ci(outcome.get_result())


@pytest.hookimpl(hookwrapper=True)
def pytest_make_collect_report(collector):
    outcome = yield
    _fail_if_skipped_in_ci(outcome.get_result())
