"""`flextrack serve`: run the PoseEstimation gRPC server, or check a running one's health."""

from __future__ import annotations

import argparse
import asyncio
import ipaddress
import logging
import os
import sys
import time
from pathlib import Path

from flextrack.assets import default_config_path

DEFAULT_CONFIG = default_config_path()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Serve flextrack.v1.PoseEstimation (Estimate, Track, ListEstimators) with gRPC health checking and server "
        "reflection. Logs are JSON lines on stderr. SIGTERM drains (health NOT_SERVING for --drain-s while still "
        "serving) then stops gracefully (exit 0); SIGINT stops without the drain.")
    parser.add_argument("--config", type=Path, default=DEFAULT_CONFIG,
                        help="TOML file with [server], [objects.<id>] and [[estimators]] (docs/service.md)")
    add_object_arguments(parser)
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on: loopback by default; any other address (0.0.0.0 for all) needs "
                             "TLS (--tls-cert) or tokens (--token-file), or --insecure-public")
    parser.add_argument("--insecure-public", action="store_true",
                        help="allow listening on a non-loopback --host without TLS or tokens: anyone who reaches the "
                             "port can call the service (behind a private network or a mesh that authenticates)")
    parser.add_argument("--port", type=int, default=50051, help="port to listen on (0 = any free port)")
    parser.add_argument("--max-message-mb", type=float, default=8.0, help="largest request/response in MiB")
    parser.add_argument("--grace-s", type=float, default=5.0,
                        help="on SIGTERM/SIGINT, seconds in-flight calls get to finish")
    parser.add_argument("--drain-s", type=float, default=5.0,
                        help="on SIGTERM, seconds health says NOT_SERVING while calls are still served, before the "
                             "socket closes (readiness probes fail first; a second signal ends it)")
    parser.add_argument("--workers", type=int, default=4, help="threads that run estimator calls")
    parser.add_argument("--gil-switch-ms", type=float, default=0.5,
                        help="the longest a thread holds Python's GIL while others wait for it (Python's default is "
                             "5): gRPC's poller thread and the estimator threads wait on the busy event loop, and "
                             "every new call or answered frame waited with them (docs/operations.md)")
    parser.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"],
                        help="JSON log lines on stderr from this level up (default: %(default)s)")
    parser.add_argument("--check", metavar="ADDR",
                        help="do not serve: ask the server at ADDR (host:port) for its health; exit 0 if SERVING")
    from service import hardening

    hardening.add_arguments(parser)


def add_object_arguments(parser: argparse.ArgumentParser) -> None:
    """--objects and --prepare-processes, shared by `flextrack serve` and `flextrack prepare`."""
    parser.add_argument("--objects", type=Path, action="append", default=[], metavar="DIR",
                        help="a BOP models folder (obj_NNNNNN.ply in mm, models_info.json beside them): every model is "
                             "served under its file stem (obj_000006) by the config's region estimators and the "
                             "chained ones built on them; their viewpoint models are built (or read from the cache "
                             "`flextrack prepare` fills) before health says SERVING (repeatable; docs/service.md)")
    parser.add_argument("--prepare-processes", type=int, default=default_processes(), metavar="N",
                        help="processes that build the viewpoint models of --objects at once (default: %(default)s, "
                             "the CPUs this process may run on)")


def default_processes() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def load_registry(config: Path, object_models: list, processes: int | None = None):
    """The config's estimators with the --objects models added, their viewpoint models built or read from the
    cache (what `flextrack serve` does before it reports SERVING)."""
    from estimators.registry import EstimatorRegistry

    registry = EstimatorRegistry.from_config(config, object_models)
    if object_models:
        start = time.perf_counter()
        records = registry.prepare([m.object_id for m in object_models], processes)
        logging.getLogger("flextrack.service").info("viewpoint models ready", extra={
            "objects": sorted({r["object"] for r in records}), "built": sum(r["built"] for r in records),
            "from_cache": sum(not r["built"] for r in records), "seconds": round(time.perf_counter() - start, 2)})
    return registry


def check(address: str, timeout_s: float = 3.0) -> int:
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    with grpc.insecure_channel(address) as channel:
        try:
            reply = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=timeout_s)
        except grpc.RpcError as exc:
            print(f"{address}: {exc.code().name}: {exc.details()}", file=sys.stderr)
            return 1
    print(f"{address}: {health_pb2.HealthCheckResponse.ServingStatus.Name(reply.status)}")
    return 0 if reply.status == health_pb2.HealthCheckResponse.SERVING else 1


def run(args: argparse.Namespace) -> int:
    if args.check:
        return check(args.check)
    from service import server

    server.configure_logging(args.log_level)
    if not args.config.is_file():
        print(f"flextrack serve: config file {args.config} not found", file=sys.stderr)
        return 2
    try:  # a config that is not TOML at all: one line now, not a log record after the server started
        import tomllib

        tomllib.loads(args.config.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        print(f"flextrack serve: {args.config}: not valid TOML ({exc})", file=sys.stderr)
        return 2
    from service.hardening import Hardening

    try:
        hardening = Hardening.from_args(args)
    except ValueError as exc:
        print(f"flextrack serve: {exc}", file=sys.stderr)
        return 2
    if not is_loopback(args.host) and not hardening.authenticates and not args.insecure_public:
        print(f"flextrack serve: refusing to listen on {args.host} without TLS or tokens; give --tls-cert/--tls-key or "
              f"--token-file, or --insecure-public to expose it unauthenticated", file=sys.stderr)
        return 2
    if not 0 <= args.port <= 65535:
        print(f"flextrack serve: --port must be 0..65535 (0: any free port), got {args.port}", file=sys.stderr)
        return 2
    if not args.drain_s >= 0:
        print(f"flextrack serve: --drain-s must be >= 0, got {args.drain_s}", file=sys.stderr)
        return 2
    if args.workers < 1 or not args.max_message_mb > 0 or not args.grace_s >= 0:
        print(f"flextrack serve: --workers must be >= 1, --max-message-mb > 0 and --grace-s >= 0, got "
              f"{args.workers}, {args.max_message_mb:g} and {args.grace_s:g}", file=sys.stderr)
        return 2
    if not args.gil_switch_ms > 0:
        print(f"flextrack serve: --gil-switch-ms must be > 0, got {args.gil_switch_ms}", file=sys.stderr)
        return 2
    if args.prepare_processes < 1:
        print(f"flextrack serve: --prepare-processes must be >= 1, got {args.prepare_processes}", file=sys.stderr)
        return 2
    from estimators.objects import load_object_folders

    try:  # before listening: a bad folder or mesh is the command line's mistake, said in one line
        object_models = load_object_folders(args.objects)
    except ValueError as exc:
        print(f"flextrack serve: --objects: {exc}", file=sys.stderr)
        return 2
    sys.setswitchinterval(args.gil_switch_ms / 1e3)  # this process is the server's alone
    try:
        return asyncio.run(server.serve(lambda: load_registry(args.config, object_models, args.prepare_processes),
                                        args.host, args.port,
                                        args.max_message_mb, args.grace_s, args.workers, hardening=hardening,
                                        drain_s=args.drain_s))
    except OSError as exc:  # the port is taken (PortInUse), or the metrics port is: one line, no trace
        print(f"flextrack serve: {exc}", file=sys.stderr)
        return 1


def is_loopback(host: str) -> bool:
    """Whether `host` is a loopback address (127.0.0.0/8, ::1, localhost): reachable from this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: it may resolve to anything
