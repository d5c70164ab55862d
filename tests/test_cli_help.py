"""`flextrack COMMAND --help` tells the truth (issue 19, point 14): every option with a default says it once, as
the parser has it; every command shows examples, and they parse."""

from __future__ import annotations

import argparse
import importlib
import re
import shlex

import pytest

from flextrack.cli import COMMANDS, command_parser
from flextrack.cli_help import EXAMPLES, DefaultsFormatter, has_default, shown, subparsers

STATED = re.compile(r"\(default:? ([^)]*)\)")


def parsers():
    for name, (module, _) in COMMANDS.items():
        parser = command_parser(name, importlib.import_module(module))
        yield name, parser
        for sub in subparsers(parser):
            yield name, sub


def _same(stated: str, default) -> bool:
    text = shown(default)
    if stated == text or stated.startswith((text + " ", text + ",")):
        return True
    try:
        return float(stated.split()[0].rstrip(",;")) == float(default)
    except (TypeError, ValueError):
        return False


@pytest.mark.parametrize("name", list(COMMANDS))
def test_each_default_is_stated_once_and_is_the_parsers(name):
    problems = []
    for command, parser in parsers():
        if command != name:
            continue
        formatter = DefaultsFormatter(parser.prog)
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)) or not action.option_strings:
                continue
            option = action.option_strings[-1]
            if has_default(action) and not action.help:
                problems.append(f"{parser.prog} {option}: no help, so its default {shown(action.default)} is not shown")
                continue
            text = formatter._expand_help(action) if action.help else ""
            stated = STATED.findall(text)
            if len(stated) > 1:
                problems.append(f"{parser.prog} {option}: states {len(stated)} defaults: {text!r}")
            elif has_default(action) and not (stated and _same(stated[0], action.default)):
                problems.append(f"{parser.prog} {option}: help says {stated} but the default is "
                                f"{shown(action.default)!r}: {text!r}")
    assert not problems, "\n".join(problems)


@pytest.mark.parametrize("name", list(COMMANDS))
def test_each_command_shows_examples_that_parse(name):
    parser = command_parser(name, importlib.import_module(COMMANDS[name][0]))
    assert EXAMPLES.get(name), f"flextrack {name} has no examples"
    assert "examples:\n  flextrack " + name in parser.format_help()
    for line in EXAMPLES[name]:
        parser.parse_args(shlex.split(line.split(" #")[0])[2:])  # SystemExit (a failure) if it does not parse


def test_progress_is_a_line_every_few_seconds_off_a_terminal_and_a_live_line_on_one():
    import io

    import numpy as np

    from flextrack.geometry.camera import PinholeCamera
    from flextrack.runners.live import Progress
    from flextrack.runners.progress import ProgressPrinter
    from flextrack.runners.results import TrackRecord

    record = TrackRecord(PinholeCamera.linemod(), np.zeros((1, 3)))
    now = [0.0]
    out = io.StringIO()
    printer = ProgressPrinter(out, every_s=5.0, clock=lambda: now[0], tty=False)
    for k in range(21):  # 20 s of wall time, a frame a second
        now[0] = float(k)
        printer(Progress(k * 0.5, 10.0, record, "FINE", True))
    assert len(out.getvalue().splitlines()) == 4 and "t 2.5/10.0 s (25 %)" in out.getvalue()
    tty = io.StringIO()
    printer = ProgressPrinter(tty, clock=lambda: now[0], tty=True)
    printer(Progress(10.0, 10.0, record, "FINE", True))  # the last one always shows, and ends the line
    assert tty.getvalue().startswith("\r") and tty.getvalue().endswith("\n")


def test_track_without_live_shows_progress(tmp_path, capsys):
    from flextrack.cli import main
    from flextrack.testing.toy_sequence import write_orbit_sequence

    seq = write_orbit_sequence(tmp_path / "orbit", frames=20)
    assert main(["track", str(seq.root), "--no-plots", "--progress-every", "0", "--out", str(tmp_path / "o")]) == 0
    assert "t 0.0/" in capsys.readouterr().err


@pytest.mark.parametrize("name, argv, dest, value", [
    ("track", ["SEQ", "--out", "o", "--preset", "paper"], "tracker", "paper"),
    ("experiment", ["euroc", "--out", "o", "--preset", "paper"], "tracker", "paper"),
    ("bench", ["tracker", "--fusion", "paper"], "tracker", "paper"),
    ("bench", ["sdk-memory", "--duration-s", "60"], "duration", 60.0),
])
def test_one_name_per_concept_and_the_old_names_still_run_saying_so(name, argv, dest, value, capsys):
    """Issue 31 item 10: --tracker names the tracker everywhere (was --preset, --fusion, --tracker), --duration
    the length (was also --duration-s); the old names are hidden aliases that say they are deprecated."""
    parser = command_parser(name, importlib.import_module(COMMANDS[name][0]))
    args = parser.parse_args(argv)
    assert getattr(args, dest) == value
    old = next(a for a in argv if a in ("--preset", "--fusion", "--duration-s"))
    assert f"{old} is deprecated; use --{dest}" in capsys.readouterr().err
    help_text = parser.format_help() if name != "bench" else ""
    assert old not in help_text
