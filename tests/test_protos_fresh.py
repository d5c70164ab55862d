"""The committed wire code must be exactly what `make protos` generates from protos/."""

from pathlib import Path

import pytest

from flextrack import protogen

pytest.importorskip("grpc_tools")


def test_generated_code_is_not_stale(tmp_path: Path):
    fresh = protogen.generate(tmp_path)
    assert fresh, "protoc generated nothing"
    for path in fresh:
        committed = protogen.REPO / path.relative_to(tmp_path)
        assert committed.exists(), f"{committed} is missing: run `make protos`"
        assert committed.read_bytes() == path.read_bytes(), f"{committed} is stale: run `make protos`"
