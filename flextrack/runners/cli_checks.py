"""Checks a command makes on its arguments before any work, each giving one line that says what is wrong and
what to do (None when all is well): an output folder that is a file, a server address that is malformed or where
nothing listens, a number out of its range."""

from __future__ import annotations

from pathlib import Path


def out_folder_problem(out: Path | None, option: str = "--out") -> str | None:
    """An output folder path that names an existing file."""
    if out is not None and out.exists() and not out.is_dir():
        return f"{option} {out} is an existing file, not a folder; give a folder (it is created if missing)"
    return None


def address_problem(address: str, option: str = "--server") -> str | None:
    """An address that does not read HOST:PORT with a port in 1..65535 (grpc URIs such as dns:/// pass)."""
    if "://" in address or address.startswith(("ipv4:", "ipv6:", "unix:")):
        return None
    host, sep, port = address.strip().rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        return f"{option} {address!r}: expected HOST:PORT with a port in 1..65535, e.g. 127.0.0.1:50051"
    return None


def server_problem(address: str, timeout_s: float = 3.0, option: str = "--server") -> str | None:
    """A malformed address, or one where no gRPC server is ready within `timeout_s`."""
    problem = address_problem(address, option)
    if problem:
        return problem
    import grpc

    from flextrack.runners.backends import wait_ready

    channel = grpc.insecure_channel(address)
    try:
        wait_ready(channel, address, timeout_s)
    except ConnectionError as exc:
        return str(exc)
    finally:
        channel.close()
    return None


def number_problem(option: str, value: float | None, low: float, high: float, *, low_closed: bool = False) -> str | None:
    """A number outside (low, high] (or [low, high] with `low_closed`): inf, nan, a negative size, a rate no
    machine keeps up with. None (the option left out) passes."""
    import math

    if value is None:
        return None
    inside = math.isfinite(value) and (low <= value if low_closed else low < value) and value <= high
    if inside:
        return None
    bracket = "[" if low_closed else "("
    return f"{option} must be a number in {bracket}{low:g}, {high:g}], got {value:g}"


def numbers_problem(checks) -> str | None:
    """The first problem of `number_problem(*check)` over (option, value, low, high[, low_closed]) tuples."""
    for check in checks:
        problem = number_problem(*check[:4], low_closed=len(check) > 4 and check[4])
        if problem:
            return problem
    return None


def deprecated_alias(parser, old: str, new: str, **kwargs) -> None:
    """Accept option `old` for `new` (same destination; `kwargs` as `new`'s: type, choices), hidden from --help,
    with a line on stderr when used: one name per concept, and yesterday's commands still run."""
    import argparse
    import sys

    class Alias(argparse.Action):
        def __call__(self, parser, namespace, values, option_string=None):
            print(f"{parser.prog}: {old} is deprecated; use {new}", file=sys.stderr)
            setattr(namespace, self.dest, values)

    parser.add_argument(old, dest=new.lstrip("-").replace("-", "_"), action=Alias, help=argparse.SUPPRESS,
                        default=argparse.SUPPRESS, **kwargs)
