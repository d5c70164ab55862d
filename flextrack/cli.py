"""The `flextrack` command: a thin dispatcher over the libraries.

Each subcommand lives in its own module, which exposes `add_arguments(parser)` and
`run(args) -> int`; it is imported only when chosen, so `flextrack --help` stays fast and a
light install (client SDK only) can still run the commands it has the dependencies for.
"""

from __future__ import annotations

import argparse
import importlib
import sys

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("flextrack.runners.demo", "start a backend, track a simulated sequence live over gRPC, print errors, write plots"),
    "serve": ("service.cli", "run the PoseEstimation gRPC server"),
    "prepare": ("service.prepare_cli", "build the region estimators' viewpoint models of your objects into the cache"),
    "guide-view": ("flextrack.guide_view", "draw the outline a user lines an object up with, and the pose it stands for"),
    "simulate": ("flextrack.simulator.cli", "generate a synthetic sequence folder (trajectory, IMU, ground truth, frames)"),
    "convert-euroc": ("flextrack.simulator.euroc_cli", "turn a EuRoC IMU + ground-truth recording into a sequence folder"),
    "calibrate": ("flextrack.calibration.cli", "an IMU's noise, bias walk, time offset and lever arm from a recording with ground truth"),
    "track": ("flextrack.runners.track_cli", "replay a sequence folder through the tracker and report its errors"),
    "experiment": ("flextrack.experiments.cli", "rerun the paper's experiments (table2, ablation, timing, euroc) and the filter's own (filter, bound)"),
    "train": ("flextrack.training.cli", "train the PVNet-style network on rendered views and export it to ONNX"),
    "bench": ("flextrack.benchmarks.cli", "benchmarks that print figures: service throughput and capacity, the tracker core, estimators"),
    "loadtest": ("flextrack.loadtest.cli", "load-test a running service with many devices (Track streams or Estimate calls)"),
    "report": ("flextrack.report", "regenerate the README's and docs' result sections from docs/results/"),
    "evaluate": ("flextrack.evaluation.cli", "evaluate estimators: prior (score with priors around the ground truth), nees (covariance calibration), gt-offset (a dataset's truth against its images)"),
}


# The extra (pyproject.toml) that brings a missing module; the rest come with `server`.
EXTRAS = {"torch": "train", "onnx": "train", "pyrender": "sim", "matplotlib": "sim", "tqdm": "sim"}


def extra_for(missing_module: str | None) -> str:
    return EXTRAS.get((missing_module or "").split(".")[0], "server")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="flextrack",
        description="Flexible-frame-rate vision-aided inertial 6DoF object tracking (client SDK, gRPC backend, "
        "simulator and experiments). Run `flextrack COMMAND --help` for a command's options.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name, (_, help_text) in COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    return parser


def command_parser(name: str, module) -> argparse.ArgumentParser:
    """`flextrack NAME`'s parser: the module's options, their true defaults and the command's examples."""
    from flextrack.cli_help import DefaultsFormatter, finish

    parser = argparse.ArgumentParser(prog=f"flextrack {name}", description=COMMANDS[name][1],
                                     formatter_class=DefaultsFormatter)
    module.add_arguments(parser)
    return finish(parser, name)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser()
    if not argv:
        parser.print_help(sys.stderr)
        return 2
    if argv[0] not in COMMANDS:
        parser.parse_args(argv)  # --help exits 0; anything else is an argparse error (exit 2)
        return 2
    name, rest = argv[0], argv[1:]
    module_name = COMMANDS[name][0]
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        print(f"flextrack {name}: cannot load {module_name} ({exc}); install the extra it needs: "
              f"pip install 'flextrack[{extra_for(exc.name)}]' (in a checkout: make setup)", file=sys.stderr)
        return 2
    cmd_parser = command_parser(name, module)
    return int(module.run(cmd_parser.parse_args(rest)) or 0)


if __name__ == "__main__":
    sys.exit(main())
