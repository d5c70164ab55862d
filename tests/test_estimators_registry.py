"""Registry: estimators from TOML (paths relative to the file), from entry points, clear errors."""

import textwrap
from pathlib import Path

import pytest
import trimesh

from estimators.base import EstimateInput, InvalidInput, UnknownEstimator, UnknownObject
from estimators.gt_oracle import GtOracleEstimator
from estimators.objects import ObjectModel, load_object_folder
from estimators.pnp import PnpEstimator
from estimators.registry import EstimatorRegistry, known_kinds
from flextrack import assets
from flextrack.formats import bop
from flextrack.testing.toy_sequence import write_orbit_sequence


@pytest.fixture
def config(tmp_path) -> Path:
    (tmp_path / "models").mkdir()
    trimesh.creation.box(extents=(80.0, 60.0, 40.0)).export(tmp_path / "models" / "box.ply")
    write_orbit_sequence(tmp_path / "seqs" / "orbit", frames=5)
    path = tmp_path / "conf" / "server.toml"
    path.parent.mkdir()
    path.write_text(textwrap.dedent("""
        [server]
        default_estimator = "pnp"
        [objects.box]
        model = "../models/box.ply"
        [[estimators]]
        name = "gt"
        kind = "gt_oracle"
        [estimators.params]
        sequence_roots = ["../seqs"]
        noise_t_m = 0.001
        [[estimators]]
        name = "pnp"
        kind = "pnp"
        objects = ["box"]
    """))
    return path


def test_config_builds_the_named_estimators_with_relative_paths(config):
    registry = EstimatorRegistry.from_config(config)
    assert registry.names() == ["gt", "pnp"] and registry.default == "pnp"
    gt = registry.get("gt")
    assert isinstance(gt, GtOracleEstimator) and gt.sequences == ["orbit"] and gt.noise_t_m == 0.001
    assert isinstance(registry.get(""), PnpEstimator) and registry.get("pnp").objects == ["box"]
    assert registry.ready
    with pytest.raises(UnknownEstimator, match="available: \\['gt', 'pnp'\\]"):
        registry.get("pvnet")


@pytest.mark.parametrize("edit, message", [
    (('kind = "pnp"', 'kind = "magic"'), "unknown kind 'magic'; known kinds: .*gt_oracle.*pnp"),
    (("noise_t_m", "noise_tm"), "unknown parameter.*noise_tm"),
    (('objects = ["box"]', 'objects = ["cup"]'), "cup"),
    (('default_estimator = "pnp"', 'default_estimator = "x"'), "default estimator 'x'"),
    (("[server]", "[server"), "not valid TOML"),
])
def test_config_mistakes_get_clear_errors(config, edit, message):
    config.write_text(config.read_text().replace(*edit))
    with pytest.raises(Exception, match=message):
        EstimatorRegistry.from_config(config)


def test_a_third_party_kind_is_found_through_its_entry_point(tmp_path, monkeypatch, config):
    """A package installed beside flextrack (a dist-info with an entry point) adds a kind."""
    (tmp_path / "thirdparty_est.py").write_text(textwrap.dedent("""
        from estimators.base import Estimator
        class Constant(Estimator):
            kind = "constant"
            def __init__(self, spec):
                super().__init__(spec.name, spec.object_ids)
                self.value = spec.params["value"]
    """))
    dist = tmp_path / "thirdparty_est-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: thirdparty-est\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[flextrack.estimators]\nconstant = thirdparty_est:Constant\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert "constant" in known_kinds()
    config.write_text(config.read_text() + '[[estimators]]\nname = "c"\nkind = "constant"\n[estimators.params]\nvalue = 7\n')
    assert EstimatorRegistry.from_config(config).get("c").value == 7


def test_the_default_config_loads():
    if not assets.default_object_model().exists():
        pytest.skip("the default object model flextrack/assets/objects/default is absent")
    registry = EstimatorRegistry.from_config(assets.default_config_path())
    assert {"gt_oracle", "gt_noisy", "pnp"} <= set(registry.names())
    assert registry.get("gt_noisy").noise_t_m == 0.003


def _folder_object(tmp_path) -> ObjectModel:
    folder = tmp_path / "mine"
    folder.mkdir()
    trimesh.creation.icosphere(subdivisions=1, radius=40.0).export(folder / "obj_000007.ply")
    bop.write_models_info(folder / "models_info.json", {7: {"diameter": 80.0}})
    (model,) = load_object_folder(folder)
    return model


def test_objects_from_a_folder_join_the_region_estimators_and_the_chains_built_on_them(config, tmp_path):
    config.write_text(config.read_text() + textwrap.dedent("""
        [[estimators]]
        name = "region"
        kind = "region"
        objects = ["box"]
        [estimators.params]
        cache_dir = "cache"
        views_subdivisions = 1
        [[estimators]]
        name = "chain"
        kind = "chained"
        [estimators.params]
        global = "pnp"
        local = "region"
    """))
    mine = _folder_object(tmp_path)
    registry = EstimatorRegistry.from_config(config, [mine])
    assert registry.get("region").objects == ["box", "obj_000007"] and registry.get("pnp").objects == ["box"]
    assert registry.get("chain").objects == ["box", "obj_000007"]
    assert registry.objects.get("obj_000007") is mine
    (record,) = registry.prepare(["obj_000007"], processes=1)
    assert record["built"] and Path(record["cache"]).is_file() and Path(record["cache"]).parent == config.parent / "cache"
    assert registry.prepare(["obj_000007"], processes=1)[0]["built"] is False  # the cache is read, not rebuilt
    chain = registry.get("chain")
    with pytest.raises(InvalidInput, match="'obj_000007' only from a prior: its global part 'pnp' does not know it"):
        chain.estimate(EstimateInput(frame_id=0, capture_time_ns=0, object_id="obj_000007"))
    with pytest.raises(UnknownObject, match="ghost"):
        chain.estimate(EstimateInput(frame_id=0, capture_time_ns=0, object_id="ghost"))


def test_objects_from_a_folder_need_a_region_estimator_and_an_id_of_their_own(config, tmp_path):
    mine = _folder_object(tmp_path)
    with pytest.raises(ValueError, match="no estimator of kind region"):
        EstimatorRegistry.from_config(config, [mine])
    clash = ObjectModel(**{**vars(mine), "object_id": "box"})
    config.write_text(config.read_text() + '[[estimators]]\nname = "region"\nkind = "region"\n')
    with pytest.raises(ValueError, match="'box' of .* is also an \\[objects\\] entry"):
        EstimatorRegistry.from_config(config, [clash])
