"""`flextrack prepare`: build the region estimators' viewpoint models into the user's cache ahead of serving.

A viewpoint model takes ~20 s of CPU per mesh; `flextrack serve` builds the missing ones of --objects
before it reports SERVING, and reads the rest from the cache this command fills (keyed by the mesh
and the options, so a changed mesh is rebuilt). Run it once per machine or image, with the same
--config and --objects the server will get.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from service.cli import DEFAULT_CONFIG, add_object_arguments


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = ("Build the region estimators' viewpoint models into the user's cache ahead of serving. "
                          + __doc__.split("\n\n")[1].replace("\n", " "))
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG,
                        help="the server config (TOML) whose region estimators (and their options) the models are for")
    add_object_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from estimators.objects import load_object_folders
    from estimators.registry import EstimatorRegistry

    if not args.config.is_file():
        print(f"flextrack prepare: config file {args.config} not found", file=sys.stderr)
        return 2
    if args.prepare_processes < 1:
        print(f"flextrack prepare: --prepare-processes must be >= 1, got {args.prepare_processes}", file=sys.stderr)
        return 2
    try:  # everything read and checked before anything is built or written
        object_models = load_object_folders(args.objects)
        registry = EstimatorRegistry.from_config(args.config, object_models)
    except (ValueError, FileNotFoundError) as exc:
        print(f"flextrack prepare: {exc}", file=sys.stderr)
        return 2
    start = time.perf_counter()
    ids = [m.object_id for m in object_models] or None  # without --objects: every region object of the config
    records = registry.prepare(ids, args.prepare_processes)
    if not records:
        print(f"flextrack prepare: {args.config} declares no region estimator: nothing to prepare", file=sys.stderr)
        return 2
    for r in records:
        print(f"{r['estimator']:>16} {r['object']:<12} {'built' if r['built'] else 'cached':<6} {r['cache']}")
    print(f"{sum(r['built'] for r in records)} built, {sum(not r['built'] for r in records)} already cached, "
          f"{time.perf_counter() - start:.1f} s")
    return 0
