"""The built wheel, installed into a fresh virtual environment outside the checkout, works on its own.

The wheel is built from a copy of the tree (the files a clone would have), installed with --no-deps into a
new venv whose only view of the dependencies is a .pth line naming the project venv's site-packages (no
downloads; .pth files there, among them the checkout's editable-install finder, are not processed). From a
folder outside the checkout it then simulates a short sequence, tracks it, and serves the default config
(the default object and the shipped model found as package data) until `serve --check` says SERVING.
"""

import os
import shutil
import socket
import subprocess
import sys
import sysconfig
import time
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
TOP_LEVEL = {"flextrack", "service", "client_sdk", "estimators"}  # the design card's names, nothing else

pytestmark = pytest.mark.slow


def _run(args, cwd, env, timeout=180) -> subprocess.CompletedProcess:
    done = subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout, check=False)
    assert done.returncode == 0, f"{args}: rc {done.returncode}\n{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    return done


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    """(venv python, the wheel, a clean environment, a work folder outside the checkout)."""
    root = tmp_path_factory.mktemp("wheel")
    assert not root.is_relative_to(REPO)
    # the tree as a clone has it: tracked files plus new ones git does not ignore (no build/, no .venv)
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"], cwd=REPO,
                            capture_output=True, check=True).stdout.decode().split("\0")
    src = root / "src"
    for rel in filter(None, listed):
        if (REPO / rel).is_file():
            (src / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / rel, src / rel)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV", "PYTHONHOME")}
    dist = root / "dist"
    _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "--wheel-dir", str(dist),
          str(src)], cwd=root, env=env, timeout=300)
    (wheel,) = dist.glob("flextrack-*.whl")

    venv = root / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", str(venv)], cwd=root, env=env)
    python = venv / "bin" / "python"
    purelib = Path(subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                                  capture_output=True, text=True, check=True).stdout.strip())
    # the dependencies, already installed in the project venv, without its .pth files (the editable finder)
    (purelib / "_flextrack_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    _run([sys.executable, "-m", "pip", "--python", str(python), "install", "-q", "--no-deps", "--no-index",
          str(wheel)], cwd=root, env=env, timeout=300)
    work = root / "work"
    work.mkdir()
    env["PATH"] = f"{venv / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    return python, wheel, env, work


def test_the_wheel_installs_only_the_design_cards_top_level_names(installed):
    _, wheel, _, _ = installed
    with zipfile.ZipFile(wheel) as zf:
        names = zf.namelist()
        (record,) = [n for n in names if n.endswith(".dist-info/RECORD")]
        rows = zf.read(record).decode().splitlines()
        top_level = [n for n in names if n.endswith(".dist-info/top_level.txt")]
        declared = set(zf.read(top_level[0]).decode().split()) if top_level else TOP_LEVEL
    installed_names = {row.split(",")[0].split("/")[0] for row in rows if row}
    installed_names = {n.removesuffix(".py") for n in installed_names if not n.endswith((".dist-info", ".data"))}
    assert installed_names == TOP_LEVEL
    assert declared == TOP_LEVEL
    # package data: the shipped model and the default config ride in the wheel; the default object is not
    # tracked (the clone this wheel was built from has none), and the install generates it on first use
    for path in ("flextrack/assets/models/pvnet_default/pvnet.onnx", "service/default_config.toml"):
        assert path in names, path
    assert not any(n.startswith("flextrack/assets/objects/") for n in names)


def test_it_imports_from_the_fresh_venv_not_the_checkout(installed):
    python, _, env, work = installed
    code = ("import client_sdk, estimators, flextrack, service; from flextrack import assets; "
            "print(flextrack.__file__); print(service.__file__); print(client_sdk.__file__); "
            "print(estimators.__file__); print(assets.default_object_model()); print(assets.pvnet_model_path())")
    lines = _run([str(python), "-c", code], cwd=work, env=env).stdout.split()
    venv = python.parent.parent
    for line in lines:
        assert Path(line).is_relative_to(venv), f"{line} is not in the fresh venv {venv}"
        assert not Path(line).is_relative_to(REPO), line
        assert Path(line).is_file(), line


def test_simulate_track_and_serve_from_the_install(installed):
    python, _, env, work = installed
    flextrack = str(python.parent / "flextrack")
    _run([flextrack, "simulate", "--motion", "circular", "--level", "medium", "--duration", "2", "--fps", "30",
          "--seed", "0", "--no-plots", "--out", "seq"], cwd=work, env=env)
    _run([flextrack, "track", "seq", "--backend", "gt", "--no-plots", "--out", "track"], cwd=work, env=env)
    assert list((work / "track").glob("*summary.json"))

    address = f"127.0.0.1:{_free_port()}"
    server = subprocess.Popen([flextrack, "serve", "--host", "127.0.0.1", "--port", address.rsplit(":", 1)[1],
                               "--log-level", "WARNING"], cwd=work, env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while True:
            check = subprocess.run([flextrack, "serve", "--check", address], cwd=work, env=env, capture_output=True,
                                   text=True, timeout=60, check=False)
            if check.returncode == 0:
                break
            assert server.poll() is None, f"the server exited: {server.communicate()[1][-3000:]}"
            assert time.monotonic() < deadline, check.stdout + check.stderr
            time.sleep(0.5)
        assert "SERVING" in check.stdout
    finally:
        server.terminate()
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
