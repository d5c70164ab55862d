"""The backend installs with `pip install flextrack[server]` alone: every third-party module that
`service/` and `estimators/` import is a dependency of the base install or of the server extra
(a container built from the wheel failed to load the default config when one was missing)."""

import ast
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# distribution name -> the import name it provides, where they differ
IMPORT_NAME = {"opencv-python-headless": "cv2", "pyyaml": "yaml", "pillow": "PIL", "prometheus-client": "prometheus_client",
               "grpcio": "grpc", "grpcio-health-checking": "grpc_health", "grpcio-reflection": "grpc_reflection",
               "protobuf": "google"}
OURS = {"service", "estimators", "client_sdk", "flextrack"}


def _declared() -> set[str]:
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    names = set()
    for spec in project["dependencies"] + project["optional-dependencies"]["server"]:
        dist = spec.split(">")[0].split("=")[0].split("[")[0].strip().lower()
        names.add(IMPORT_NAME.get(dist, dist.replace("-", "_")))
    return names


def _imports(folder: Path) -> dict[str, str]:
    found = {}
    for path in folder.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                mods = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                mods = [node.module]
            else:
                continue
            for mod in mods:
                found.setdefault(mod.split(".")[0], str(path.relative_to(REPO)))
    return found


def test_the_backend_imports_only_what_the_server_extra_installs():
    allowed = _declared() | OURS | set(sys.stdlib_module_names) | {"__future__"}
    used = {**_imports(REPO / "service"), **_imports(REPO / "estimators")}
    missing = {mod: where for mod, where in used.items() if mod not in allowed}
    assert not missing, f"imported by the backend but not in the server extra: {missing}"
