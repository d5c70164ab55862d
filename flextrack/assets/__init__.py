"""The files flextrack ships as package data, found through `importlib.resources` (so a wheel works).

- the project's default object (`objects/default/models/`: `obj_000001.ply` in mm + `models_info.json`,
  written by `python -m flextrack.simulator.default_object`);
- the shipped PVNet-style model (`models/pvnet_default/`: `pvnet.onnx` and its `MODEL_CARD.md`);
- the backend's default config (`service/default_config.toml`, which names the two above as
  `package:flextrack.assets/...`, see `resolve`).

Every part that needs one of them asks this module; nothing walks up from a source file.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

PACKAGE_PREFIX = "package:"  # "package:PKG/REL/PATH": a file shipped inside an importable package


def _path(package: str, *parts: str) -> Path:
    # Installed packages (wheel or editable) live on the file system, so the Traversable is a real path.
    return Path(str(files(package).joinpath(*parts)))


def default_object_dir() -> Path:
    """The default object's BOP models folder (`obj_000001.ply` and `models_info.json`)."""
    return _path(__name__, "objects", "default", "models")


def default_object_model() -> Path:
    """The default object's model, a BOP .ply in mm."""
    return default_object_dir() / "obj_000001.ply"


def object_model(spec: str | Path) -> Path:
    """'default' -> the project's default object; otherwise a .ply path (BOP, mm). The file must exist."""
    path = default_object_model() if str(spec) == "default" else Path(spec)
    if not path.is_file():
        raise FileNotFoundError(f"object model {path} not found (give 'default' or a BOP .ply in mm)")
    return path


def pvnet_model_dir() -> Path:
    """The shipped PVNet-style model's folder (`pvnet.onnx`, `MODEL_CARD.md`)."""
    return _path(__name__, "models", "pvnet_default")


def pvnet_model_path() -> Path:
    """The shipped PVNet-style model, ONNX."""
    return pvnet_model_dir() / "pvnet.onnx"


def default_config_path() -> Path:
    """The backend's default config, `flextrack serve` without --config."""
    return _path("service", "default_config.toml")


def resolve(value: str | Path, base_dir: Path) -> Path:
    """A path from a config file: `package:PKG/REL` inside an installed package, else relative to `base_dir`."""
    text = str(value)
    if text.startswith(PACKAGE_PREFIX):
        package, _, rel = text[len(PACKAGE_PREFIX):].partition("/")
        return _path(package, *[p for p in rel.split("/") if p])
    return base_dir / value
