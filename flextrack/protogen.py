"""Generate the Python wire code in flextrack/v1 from protos/ (the one command: `make protos`).

The generated files are committed so that a device install needs no protoc; a test regenerates
them into a temporary folder and fails when the committed ones are stale.
"""

from __future__ import annotations

import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PROTO_ROOT = REPO / "protos"


def proto_files() -> list[Path]:
    return sorted(PROTO_ROOT.rglob("*.proto"))


def generate(out_dir: Path) -> list[Path]:
    """Run protoc (from grpcio-tools) into out_dir; returns the files written."""
    from grpc_tools import protoc  # dev dependency, imported only here

    out_dir.mkdir(parents=True, exist_ok=True)
    args = ["protoc", f"-I{PROTO_ROOT}", f"--python_out={out_dir}", f"--pyi_out={out_dir}",
            f"--grpc_python_out={out_dir}", *map(str, proto_files())]
    if protoc.main(args) != 0:
        raise RuntimeError("protoc failed: " + " ".join(args))
    return sorted(p for p in (out_dir / "flextrack").rglob("*_pb2*") if p.suffix in (".py", ".pyi"))


def main() -> int:
    for path in generate(REPO):
        print(f"generated {path.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
