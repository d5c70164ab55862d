"""`flextrack evaluate SUBCOMMAND`: evaluations of the estimators, one sub-parser per module.

Each module in SUBCOMMANDS exposes `add_arguments(parser)` and `run(args) -> int`, and is imported
only when chosen.
"""

from __future__ import annotations

import argparse
import importlib

# name -> (module, one-line help)
SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "prior": ("flextrack.evaluation.prior_eval",
              "score an estimator on a BOP folder with priors drawn around the ground truth"),
    "nees": ("flextrack.evaluation.nees_calibration",
             "are the estimators' pose covariances calibrated? mean NEES of held-out answers vs chi2(6)"),
    "gt-offset": ("flextrack.evaluation.gt_offset",
                  "does a BOP dataset's ground truth sit where its images show the objects? (vertex colours, edges)"),
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="evaluation", metavar="EVALUATION", required=True)
    for name, (module_name, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text,
                           formatter_class=argparse.ArgumentDefaultsHelpFormatter)
        p.set_defaults(_module=module_name)
        importlib.import_module(module_name).add_arguments(p)


def run(args: argparse.Namespace) -> int:
    return int(importlib.import_module(args._module).run(args) or 0)
