"""Build estimators from a TOML config and the `flextrack.estimators` entry-point group.

A kind is a factory: a class with a `from_spec(spec)` classmethod, or any callable taking an
`EstimatorSpec`. Third-party packages register kinds under the entry-point group; the kinds this
repository ships are listed in BUILTIN_KINDS too, so a source checkout works before (re)installing.

Objects can come from outside the config too (`flextrack serve --objects DIR`): each is added to the
config's objects and to every estimator of a kind that works from the mesh alone (MESH_KINDS), and so
to the composites built on those; `prepare` builds what those estimators would otherwise build on
their first request.
"""

from __future__ import annotations

import importlib
import tomllib
from dataclasses import dataclass, field
from importlib.metadata import entry_points
from pathlib import Path

from estimators.base import Estimator, UnknownEstimator
from estimators.objects import ObjectModel, ObjectRegistry
from flextrack.assets import resolve

ENTRY_POINT_GROUP = "flextrack.estimators"
BUILTIN_KINDS = {
    "gt_oracle": "estimators.gt_oracle:GtOracleEstimator",
    "pnp": "estimators.pnp:PnpEstimator",
    "pvnet": "estimators.pvnet:PvnetEstimator",
    "region": "estimators.region.estimator:RegionEstimator",
    "chained": "estimators.chained:ChainedEstimator",
}

# Kinds that need nothing of an object but its mesh: every object brought with --objects is theirs too.
MESH_KINDS = ("region",)


@dataclass
class EstimatorSpec:
    """One [[estimators]] entry of the config, with paths already resolved."""

    name: str
    kind: str
    objects: ObjectRegistry  # every object of the config
    object_ids: list[str] = field(default_factory=list)  # empty: all objects
    model: Path | None = None
    params: dict = field(default_factory=dict)
    base_dir: Path = Path(".")  # relative paths in params are relative to this (the config's folder)
    built: dict = field(default_factory=dict)  # name -> Estimator: the entries above this one, for composites

    def estimator(self, name: str) -> Estimator:
        """An estimator declared above this one (composites name their parts)."""
        if name not in self.built:
            raise ValueError(f"estimator '{self.name}' names '{name}', which is not declared above it; "
                             f"declared: {sorted(self.built)}")
        return self.built[name]

    def path(self, value: str | Path) -> Path:
        """A path from the config: relative to its folder, or `package:PKG/REL` inside an installed package."""
        return resolve(value, self.base_dir)

    def check_params(self, known: set[str]) -> None:
        unknown = set(self.params) - known
        if unknown:
            raise ValueError(f"estimator '{self.name}' (kind {self.kind}): unknown parameter(s) {sorted(unknown)}; "
                             f"known: {sorted(known)}")


def known_kinds() -> dict[str, str]:
    """kind -> 'module:attr' of its factory, entry points over the built-in table."""
    kinds = dict(BUILTIN_KINDS)
    kinds.update({ep.name: ep.value for ep in entry_points(group=ENTRY_POINT_GROUP)})
    return kinds


def build_estimator(spec: EstimatorSpec) -> Estimator:
    kinds = known_kinds()
    if spec.kind not in kinds:
        raise ValueError(f"estimator '{spec.name}': unknown kind '{spec.kind}'; known kinds: {sorted(kinds)} "
                         f"(a package adds kinds through the '{ENTRY_POINT_GROUP}' entry-point group)")
    module_name, _, attr = kinds[spec.kind].partition(":")
    factory = importlib.import_module(module_name)
    for part in attr.split("."):
        factory = getattr(factory, part)
    return factory.from_spec(spec) if hasattr(factory, "from_spec") else factory(spec)


class EstimatorRegistry:
    """Estimators by name, plus the default one that requests with an empty name get."""

    def __init__(self, estimators: list[Estimator] | tuple[Estimator, ...] = (), default: str | None = None,
                 objects: ObjectRegistry | None = None):
        self.objects = objects or ObjectRegistry()
        self._estimators: dict[str, Estimator] = {}
        self.default: str | None = None  # the first estimator added unless named
        for estimator in estimators:
            self.add(estimator)
        if default is not None:
            if default not in self._estimators:
                raise ValueError(f"default estimator '{default}' is not configured; configured: {self.names()}")
            self.default = default

    def add(self, estimator: Estimator) -> None:
        if estimator.name in self._estimators:
            raise ValueError(f"two estimators are named '{estimator.name}'")
        self._estimators[estimator.name] = estimator
        if self.default is None:
            self.default = estimator.name

    def get(self, name: str = "") -> Estimator:
        name = name or self.default or ""
        try:
            return self._estimators[name]
        except KeyError:
            raise UnknownEstimator(f"unknown estimator '{name}'; available: {self.names()}") from None

    def names(self) -> list[str]:
        return list(self._estimators)

    def __iter__(self):
        return iter(self._estimators.values())

    @property
    def ready(self) -> bool:
        return all(e.ready for e in self)

    def prepare(self, object_ids: list[str] | None = None, processes: int | None = None) -> list[dict]:
        """Build the region estimators' viewpoint models of `object_ids` (None: all their objects) into the
        cache, several processes at once, and load them, so that no request waits ~20 s for one. One record
        per (estimator, object): estimator, object, built (False: read from the cache), cache file."""
        from estimators.region.estimator import RegionEstimator
        from estimators.region.viewpoint_model import ViewpointJob, prepare_viewpoint_models

        wanted = [(e, i) for e in self if isinstance(e, RegionEstimator)
                  for i in e.objects if object_ids is None or i in object_ids]
        jobs = []
        for estimator, object_id in wanted:
            model = self.objects.get(object_id)
            jobs.append(ViewpointJob(model.vertices, model.faces, estimator.cache_dir, dict(estimator.view_options)))
        built = prepare_viewpoint_models(jobs, processes)
        for estimator, object_id in wanted:
            estimator.viewpoint_model(object_id)  # from the cache now: kept in memory before the first request
        return [{"estimator": e.name, "object": i, "built": b, "cache": str(job.path)}
                for (e, i), b, job in zip(wanted, built, jobs, strict=True)]

    @classmethod
    def from_dict(cls, doc: dict, base_dir: Path, object_models: list[ObjectModel] | tuple[ObjectModel, ...] = (),
                  ) -> EstimatorRegistry:
        """`object_models`: objects from outside the config (load_object_folder), for every MESH_KINDS estimator."""
        objects = ObjectRegistry.from_config(doc.get("objects", {}), base_dir)
        for model in object_models:
            if model.object_id in objects and objects.get(model.object_id).model_path != model.model_path:
                raise ValueError(f"object '{model.object_id}' of {model.model_path.parent} is also an [objects] "
                                 f"entry of the config ({objects.get(model.object_id).model_path})")
            objects.add(model)
        extra_ids = [m.object_id for m in object_models]
        if extra_ids and not any(e.get("kind") in MESH_KINDS for e in doc.get("estimators", [])):
            raise ValueError(f"the config declares no estimator of kind {' or '.join(MESH_KINDS)} to serve the "
                             f"objects {extra_ids} with; add one ([[estimators]] kind = \"region\")")
        estimators = []
        for entry in doc.get("estimators", []):
            unknown = set(entry) - {"name", "kind", "objects", "model", "params"}
            if unknown or "kind" not in entry:
                raise ValueError(f"[[estimators]] entry {entry.get('name', '?')}: needs `kind`, accepts name, objects, "
                                 f"model, params; unexpected {sorted(unknown)}")
            object_ids = list(entry.get("objects", []))
            if object_ids and entry.get("kind") in MESH_KINDS:
                object_ids += [i for i in extra_ids if i not in object_ids]
            for object_id in object_ids:
                objects.get(object_id)  # fail at load time, naming the object
            spec = EstimatorSpec(
                name=entry.get("name", entry["kind"]), kind=entry["kind"], objects=objects, object_ids=object_ids,
                model=resolve(entry["model"], base_dir) if "model" in entry else None,
                params=dict(entry.get("params", {})), base_dir=base_dir, built={e.name: e for e in estimators})
            estimators.append(build_estimator(spec))
        return cls(estimators, doc.get("server", {}).get("default_estimator"), objects)

    @classmethod
    def from_config(cls, path: str | Path, object_models: list[ObjectModel] | tuple[ObjectModel, ...] = (),
                    ) -> EstimatorRegistry:
        """The config's estimators; `object_models` (e.g. load_object_folder(DIR)) added as from_dict says."""
        path = Path(path)
        try:
            doc = tomllib.loads(path.read_text())
        except tomllib.TOMLDecodeError as exc:
            raise ValueError(f"{path}: not valid TOML: {exc}") from None
        return cls.from_dict(doc, path.resolve().parent, object_models)
