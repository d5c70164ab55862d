"""What every `flextrack COMMAND --help` shows beside its options: each option's default as the parser has it
(never a second, hand-written one, floats shortened), and examples of the command.

`DefaultsFormatter` appends "(default: VALUE)" to an option's help unless the help already says its default
("%(default)s", "(default ...)" or "default: ..."), or there is none to say (None, False, an empty list).
`finish(parser, name)` gives the command's parser, and each of its sub-commands' parsers, that formatter and
the command's examples as the epilog.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

# Stated defaults: "(default: X)", "(default X)", "default: X"; a help that states one gets none appended.
STATED_DEFAULT = re.compile(r"\(default\b[: ]|\bdefault: ")

EXAMPLES: dict[str, list[str]] = {
    "demo": ["flextrack demo --out out/demo",
             "flextrack demo --motion translational --level hard --fps 60 --backend gt --out out/demo_hard"],
    "serve": ["flextrack serve --port 50051",
              "flextrack serve --port 50051 --config service/default_config.toml --metrics-port 9100",
              "flextrack serve --check 127.0.0.1:50051",
              "flextrack serve --objects ../shared/data/lmo/models"],
    "prepare": ["flextrack prepare --objects ../shared/data/lmo/models",
                "flextrack prepare --config service/default_config.toml"],
    "guide-view": ["flextrack guide-view --object ../shared/data/lmo/models/obj_000006.ply --out out/guide.png",
                   ("flextrack guide-view --object MESH.ply --intrinsics 1500,1500,960,540 --size 1920x1080 "
                    "--out out/guide.png")],
    "simulate": ["flextrack simulate --motion circular --level medium --duration 30 --fps 120 --out out/seq/circ_med",
                 "flextrack simulate --motion translational --level easy --duration 10 --render --out out/seq/te"],
    "convert-euroc": ["flextrack convert-euroc --euroc ../shared/data/euroc_v1_02_medium --out out/seq/v1_02",
                      "flextrack convert-euroc --euroc MY_RECORDING --object-distance 1.2 --fps 30 --out out/seq/mine"],
    "calibrate": ["flextrack calibrate imu --data ../shared/data/phone_ar/nexus5_ar_a",
                  "flextrack calibrate imu --data MY_RECORDING --json out/calibrate_imu.json"],
    "track": ["flextrack track out/seq/circ_med --backend noisy --out out/track",
              "flextrack track out/seq/circ_med --backend pvnet --fps 30 --out out/track_pvnet",
              "flextrack track out/seq/mine --tracker paper --set px_error=15 --out out/track_mine",
              ("flextrack track out/seq/circ_med --server 127.0.0.1:50051 --backend pvnet_region --out out/server "
               "# a default `flextrack serve`; its oracles need the folder in sequence_roots")],
    "experiment": ["flextrack experiment table2 --seeds 3 --out out/table2",
                   "flextrack experiment euroc --data MY_RECORDING --fps 30 --set filter.gate_chi2=30 --out out/mine",
                   "flextrack experiment ablation --out out/ablation"],
    "train": ["flextrack train pvnet --object default --out runs/pvnet_default --minutes 10",
              "flextrack train pvnet-eval --model runs/pvnet_default/pvnet.onnx --out out/pvnet_eval"],
    "bench": ["flextrack bench service",
              "flextrack bench capacity --out out/bench_capacity",
              "flextrack bench tracker"],
    "loadtest": ["flextrack loadtest --target 127.0.0.1:50051 --clients 40 --fps 30 --duration 10 --out out/load",
                 ("flextrack loadtest --target 127.0.0.1:50051 --estimator gt_oracle --sequence SEQ_DIR --out out/load "
                  "# SEQ_DIR in the server config's sequence_roots")],
    "report": ["flextrack report --check", "flextrack report --list"],
    "evaluate": ["flextrack evaluate nees --out out/nees",
                 ("flextrack evaluate prior --bop ../shared/data/lmo --obj-id all --estimator region --fresh "
                  "--out out/prior.json"),
                 "flextrack evaluate gt-offset --bop ../shared/data/lmo --out out/gt_offset.json"],
}


def shown(value) -> str:
    """A default as help shows it: floats shortened (2.46136, not 2.461360123647604), lists space-separated."""
    if isinstance(value, float):
        return f"{value:g}"
    if isinstance(value, (list, tuple)):
        return " ".join(shown(v) for v in value)
    if isinstance(value, Path):
        return str(value)
    return str(value)


def has_default(action: argparse.Action) -> bool:
    """Whether an option has a default worth saying (not None, False, [] or suppressed)."""
    d = action.default
    return not (d is None or d is False or d == [] or d == argparse.SUPPRESS
                or isinstance(action, argparse._HelpAction))


class DefaultsFormatter(argparse.HelpFormatter):
    def _fill_text(self, text: str, width: int, indent: str) -> str:
        if text.startswith("examples:"):  # one command a line, as written
            return "".join(indent + line for line in text.splitlines(keepends=True))
        return super()._fill_text(text, width, indent)

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "%(default)" in text or STATED_DEFAULT.search(text) or not has_default(action):
            return text
        if not (action.option_strings or action.nargs in (argparse.OPTIONAL, argparse.ZERO_OR_MORE)):
            return text
        return f"{text} (default: {shown(action.default).replace('%', '%%')})".lstrip()


def subparsers(parser: argparse.ArgumentParser):
    """The parser's sub-commands' parsers, recursively."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                yield sub
                yield from subparsers(sub)


def finish(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    """The formatter and `name`'s examples on the parser and its sub-commands' parsers."""
    epilog = "examples:\n" + "\n".join(f"  {line}" for line in EXAMPLES.get(name, []))
    for p in (parser, *subparsers(parser)):
        p.formatter_class = DefaultsFormatter
        for action in p._actions:  # an option without help would not show its default at all
            if action.option_strings and not action.help and has_default(action):
                action.help = f"(default: {shown(action.default).replace('%', '%%')})"
        if not p.epilog and name in EXAMPLES:
            p.epilog = epilog
    return parser
