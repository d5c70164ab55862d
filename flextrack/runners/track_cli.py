"""`flextrack track SEQ_DIR --out DIR`: run the tracker over one sequence folder and report its errors.

By default the sequence is replayed in virtual time against a real gRPC server that this command
starts on a loopback port (bit-identical for one seed); `--live` runs it in real time through the
sleeping latency interceptor instead, and `--in-process` skips gRPC in the replay.
"""

from __future__ import annotations

import argparse
import difflib
import json
import math
import sys
from dataclasses import asdict, fields, replace
from pathlib import Path

import numpy as np

from client_sdk import FilterOptions, TrackerOptions
from client_sdk.network_model import NetworkOptions
from client_sdk.options import PRESETS, preset
from client_sdk.slowdown import PIXEL2_FACTOR
from flextrack.assets import default_config_path
from flextrack.formats import sequence as sequence_io
from flextrack.provenance import of_args
from flextrack.runners import cli_checks, exchange, scoring, session
from flextrack.runners.backends import ORACLE_BACKENDS as ORACLES
from flextrack.runners.progress import ProgressPrinter
from flextrack.runners.results import format_table


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("sequence", type=Path, metavar="SEQ_DIR", help="a sequence folder (flextrack simulate, "
                        "flextrack convert-euroc)")
    parser.add_argument("--out", type=Path, required=True, help="folder for frames.csv, summary.json, TUM files, plots")
    parser.add_argument("--backend", default="gt", help="estimator: gt or noisy (oracles served from the sequence's "
                        "ground truth), or a name from --config (e.g. pvnet)")
    parser.add_argument("--config", type=Path, help="estimator config (TOML) for the embedded server instead of the "
                        "oracles; its gt_oracle estimators are given this sequence (default: the oracles for gt and "
                        "noisy, service/default_config.toml for any other --backend)")
    parser.add_argument("--objects", type=Path, action="append", default=[], metavar="DIR",
                        help="a BOP models folder whose objects (obj_NNNNNN.ply, named by file stem) the embedded "
                        "server's region estimators serve too, as `flextrack serve --objects` (repeatable)")
    parser.add_argument("--server", help="HOST:PORT of a running server to use instead of an embedded one; it must "
                        "know the sequence: give --backend an estimator of its config (a default `flextrack serve` "
                        "has gt_oracle, gt_noisy, pvnet and pvnet_region; its oracles answer only sequences under "
                        "their sequence_roots, so list this folder's parent there, or use pvnet_region)")
    parser.add_argument("--live", action="store_true", help="run in real time, the network delays and device slowdown applied by waiting (default: a replay in virtual time)")
    parser.add_argument("--speed", type=float, default=1.0, help="with --live: play the sequence this much faster")
    parser.add_argument("--in-process", action="store_true", help="replay without gRPC (same results)")
    parser.add_argument("--fps", type=float, help="use the sequence's frames nearest to this rate, Hz (default: every frame)")
    parser.add_argument("--tracker", choices=PRESETS, default="filter",
                        help="tracker: filter (the error-state Kalman filter, for every backend) or paper (the "
                        "paper's PRM + BSCM) (default: %(default)s)")
    cli_checks.deprecated_alias(parser, "--preset", "--tracker", choices=PRESETS)
    parser.add_argument("--set", action="append", default=[], metavar="OPTION=VALUE",
                        help="override one TrackerOptions field of the --tracker's options, e.g. --set px_error=15 or a filter "
                        "option, e.g. --set filter.time_offset_std_s=0 (repeatable; numbers and true/false)")
    parser.add_argument("--no-bscm", action="store_true", help="ablation: no bias self-correction")
    parser.add_argument("--no-pia", action="store_true", help="ablation: no pose inspection")
    parser.add_argument("--imu-only", action="store_true", help="ablation: no backend after initialisation")
    parser.add_argument("--integrator", choices=("paper", "midpoint"),
                        help="the paper method's integrator (default: the preset's; the filter always uses midpoint)")
    parser.add_argument("--network", choices=("paper", "real-size", "none"), default="paper",
                        help="paper: 100 kB a request; real-size: the request's serialized size; none: no latency")
    parser.add_argument("--slowdown", type=float, default=PIXEL2_FACTOR, help="device CPU slowdown factor, 1 = none (default: %(default)g, the Pixel 2's)")
    parser.add_argument("--backend-ms", type=float, default=0.0, help="modelled backend compute time (replay)")
    parser.add_argument("--seed", type=int, default=0, help="network and Noisy-backend seed")
    parser.add_argument("--frames", action="store_true", help="send the rendered frames (rendered on demand into the "
                        "folder's rgb/); on by default for estimators other than the gt/noisy oracles")
    parser.add_argument("--no-plots", action="store_true", help="skip the error and trajectory plots")
    parser.add_argument("--progress-every", type=float, default=5.0, metavar="S",
                        help="progress on stderr: a live line on a terminal, else a line every S seconds")


def network_options(kind: str, seed: int) -> NetworkOptions:
    if kind == "none":
        return replace(NetworkOptions.zero(), seed=seed)
    return NetworkOptions(seed=seed, fixed_payload_bytes=None if kind == "real-size" else NetworkOptions().fixed_payload_bytes)


def overrides(pairs: list[str]) -> tuple[dict, dict]:
    """(tracker, filter) overrides: ["pia=false", "filter.gate_chi2=30"] -> ({"pia": False}, {"gate_chi2": 30.0});
    ValueError on a bad one."""
    known = {f.name for f in fields(TrackerOptions)} - {"filter", "fusion"}
    known_filter = {f.name for f in fields(FilterOptions)}
    out: tuple[dict, dict] = ({}, {})
    strings = {f.name for f in fields(TrackerOptions) if f.type in ("str", str)}
    for pair in pairs:
        name, sep, value = pair.partition("=")
        group, _, field_name = name.rpartition(".")
        if not sep or group not in ("", "filter"):
            raise ValueError(f"--set {pair!r}: expected OPTION=VALUE (a tracker option) or filter.NAME=VALUE")
        names = known_filter if group else known
        if field_name not in names:
            close = difflib.get_close_matches(field_name, names, n=3)
            hint = f"did you mean {', '.join(close)}?" if close else f"one of {', '.join(sorted(names))}"
            raise ValueError(f"--set {pair!r}: unknown {'filter ' if group else ''}option {field_name!r}; {hint}")
        target = out[1] if group else out[0]
        if not group and field_name in strings:
            target[field_name] = value
        elif value.lower() in ("true", "false"):
            target[field_name] = value.lower() == "true"
        else:
            try:
                target[field_name] = float(value)
            except ValueError:
                raise ValueError(f"--set {pair!r}: {value!r} is not a number or true/false") from None
    return out


def tracker_options(args) -> TrackerOptions:
    base = preset(args.tracker)
    flags = replace(base, bscm=not args.no_bscm, pia=not args.no_pia, backend_after_init=not args.imu_only,
                    integrator=args.integrator or base.integrator)
    tracker_set, filter_set = overrides(args.set)
    defaults = FilterOptions()
    for name, value in filter_set.items():  # integer options stay integers
        if isinstance(getattr(defaults, name), int) and not isinstance(value, bool):
            filter_set[name] = int(value)
    return replace(flags, filter=replace(flags.filter, **filter_set), **tracker_set)


def argument_problem(args) -> str | None:
    """One line for an argument that cannot work, before any work is done."""
    if args.speed != 1.0 and not args.live:
        return "--speed plays a --live run faster; add --live, or drop --speed (a replay runs in virtual time)"
    problem = cli_checks.numbers_problem([
        ("--speed", args.speed, 0, 1000), ("--fps", args.fps, 0, 1000), ("--slowdown", args.slowdown, 0, 100),
        ("--backend-ms", args.backend_ms, 0, 60_000, True), ("--progress-every", args.progress_every, 0, 3600, True)])
    if problem:
        return problem
    if args.config is not None and not args.config.is_file():
        return f"--config {args.config}: no such file (the default config is used when --config is left out)"
    if args.server and args.config:
        return "--config configures the embedded server; with --server the running server's own config is used"
    if args.server and args.objects:
        return "--objects configures the embedded server; a running server is given them by `flextrack serve --objects`"
    if args.objects and args.config is None and args.backend in ORACLES:
        return f"--objects serves objects with a config's region estimators; --backend {args.backend} is an oracle"
    return cli_checks.out_folder_problem(args.out)


# Kinds `track` cannot drive: what they need that its requests do not carry.
UNSUITABLE_KINDS = {
    "pnp": "pnp estimates from 2D keypoints sent with each request, and track sends frames, not keypoints "
           "(use pvnet or pvnet_region, or an oracle)",
    "region": "region only refines the device's prior and cannot give the first pose, which track's first "
              "request asks for (use pvnet_region: pvnet for the first pose, region after)",
}


def estimator_kind(backend: str, registry, server: str | None) -> str | None:
    """The kind of estimator `backend` names: in the embedded registry, or as the server lists it (None when
    it has none of that name: the first request then says so in the server's own words)."""
    if server is None:
        return next((e.kind for e in registry if e.name == backend), None)
    import grpc

    from flextrack.v1 import pose_estimation_pb2 as pb
    from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc

    with grpc.insecure_channel(server) as channel:
        listed = pb_grpc.PoseEstimationStub(channel).ListEstimators(pb.ListEstimatorsRequest(), timeout=10.0)
    return next((e.kind for e in listed.estimators if e.name == backend), None)


def first_request_refusal(seq, spec: session.RunSpec, registry) -> str | None:
    """Send the run's first request (no prior, the stand-in image) and give the server's reason when it refuses
    it (INVALID_INPUT: an unknown estimator, object or sequence; a gRPC error: a stream it does not accept), so a
    run that cannot work stops before rendering or tracking anything. None when it is answered otherwise."""
    import grpc

    from client_sdk.transport import make_request
    from flextrack import wire
    from flextrack.runners.backends import GrpcBackend, InProcessBackend
    from flextrack.runners.payload import stand_in_jpeg
    from flextrack.v1 import pose_estimation_pb2 as pb

    request = make_request(
        frame_id=int(seq.frame_ids[0]), capture_time_ns=int(seq.frame_times_ns[0]), session_id="track-probe",
        estimator=spec.backend, object_id=seq.object_id, sequence=seq.name,
        image=stand_in_jpeg(seq.camera.width, seq.camera.height), width=seq.camera.width,
        height=seq.camera.height, intrinsics=wire.intrinsics_to_pb(seq.camera))
    zero = NetworkOptions.zero()
    backend = InProcessBackend(registry, zero) if spec.server is None else GrpcBackend(spec.server, zero)
    try:
        response, _ = backend.call(request)
    except grpc.RpcError as exc:
        return f"the server at {spec.server} refused the stream: {exc.code().name}: {exc.details()}"
    finally:
        backend.close()
    if response.status != pb.EstimateResponse.INVALID_INPUT:
        return None
    where = "the embedded server" if spec.server is None else f"the server at {spec.server}"
    return f"{where} refused the first request: INVALID_INPUT: {response.message}"


def fine_only(record) -> dict:
    """Mean errors over the frames the tracker called FINE (the paper's rule, `experiment euroc`'s): on a
    recording that leaves the view, frames re-entering it before the tracker recovers (WRONG_POSE,
    TRACKING_LOST) can be hundreds of px off and dominate the mean of every frame."""
    rows = [r for r in record.scored() if r.status == "FINE"]
    mean = (lambda key: float(np.mean([getattr(r, key) for r in rows]))) if rows else (lambda key: math.nan)
    return {"frames": len(rows), "proj_px": mean("proj_px"), "pos_mm": mean("pos_mm"), "ori_deg": mean("ori_deg")}


def run(args) -> int:
    problem = argument_problem(args)
    if problem:
        print(f"flextrack track: {problem}", file=sys.stderr)
        return 2
    if args.server:
        problem = cli_checks.server_problem(args.server)
        if problem:
            print(f"flextrack track: {problem}, or drop --server to track against an embedded one", file=sys.stderr)
            return 1
    if args.config is None and args.server is None and args.backend not in ORACLES:
        args.config = default_config_path()  # pvnet, region, ...: the estimators `flextrack serve` has
    try:
        loaded = sequence_io.load(args.sequence)  # the one parse of the folder: the oracles answer from it too
        seq = session.at_fps(loaded, args.fps) if args.fps else loaded
        seq = scoring.in_view_only(seq)  # frames with the object out of view are not scored
        spec = session.RunSpec(
            backend=args.backend, network=network_options(args.network, args.seed), slowdown=args.slowdown,
            backend_compute_ms=args.backend_ms, seed=args.seed, live=args.live, speed=args.speed,
            in_process=args.in_process, config=args.config, server=args.server, objects=tuple(args.objects),
            frames=args.frames or args.backend not in ORACLES)
        options = tracker_options(args)
        clash = sorted(set(overrides(args.set)[1]) & set(exchange.declared_filter_options(loaded)))
        if clash:  # it would be replaced by the declaration
            raise ValueError(f"--set filter.{clash[0]}: {args.sequence} declares what it cannot know exactly "
                             f"(sequence.yaml {exchange.DECLARED_BY[clash[0]]}), which the tracker's {clash[0]} "
                             "is set from; edit it there")
        registry = None if args.server else session.registry_for(loaded, spec)
        kind = estimator_kind(args.backend, registry, args.server)
        if kind is None and registry is not None:
            raise ValueError(f"--backend {args.backend}: unknown estimator; available: {registry.names()} "
                             "(pass --config FILE for an estimator config that lists it)")
        if kind in UNSUITABLE_KINDS:
            print(f"flextrack track: --backend {args.backend}: {UNSUITABLE_KINDS[kind]}", file=sys.stderr)
            return 2
        refusal = first_request_refusal(seq, spec, registry)
        if refusal:
            print(f"flextrack track: {refusal}", file=sys.stderr)
            return 1
        progress = ProgressPrinter(sys.stderr, every_s=args.progress_every)
        record = session.track(seq, options, spec, progress=progress, registry=registry)
    except (FileNotFoundError, ValueError, ConnectionError, RuntimeError) as exc:
        print(f"flextrack track: {exc}", file=sys.stderr)
        return 2
    except KeyError as exc:
        print(f"flextrack track: {args.sequence}: rig.yaml lacks the field {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("\nflextrack track: interrupted", file=sys.stderr)
        return 130
    name = f"{seq.name}_{args.backend}"
    accounting = scoring.account(record)
    record.write(args.out, name, provenance=of_args(args, command="flextrack track"))
    fine = fine_only(record)
    summary_file = args.out / f"{name}_summary.json"  # what was scored, and why the rest was not
    summary_file.write_text(json.dumps(json.loads(summary_file.read_text()) | {"accounting": asdict(accounting),
                                                                                "fine_only": fine}, indent=2) + "\n")
    if not args.no_plots and accounting.scored:
        session.write_plots(record, args.out, name)
    summary = record.summarize()
    print(format_table([(name, summary)]))
    if fine["frames"] and fine["frames"] < accounting.scored:
        print(f"on the {fine['frames']} FINE frames alone (experiment euroc's rule): 2D {fine['proj_px']:.3f} px, "
              f"{fine['pos_mm']:.2f} mm, {fine['ori_deg']:.3f} deg; the table's {summary.proj_px:.3f} px also counts "
              f"the {accounting.scored - fine['frames']} frames the tracker itself called lost or wrong")
    print(accounting.describe())
    if summary.time_offset_ms == summary.time_offset_ms:  # the filter estimated it
        print(f"camera-IMU time offset (t_imu - t_camera) estimated online: {summary.time_offset_ms:.1f} ms")
    print(f"wrote {args.out}/{name}_*")
    reason = accounting.nothing_scored_reason()
    if reason:
        if record.first_refusal and not record.responses:  # the server's own words, not a guess
            reason = f"the backend answered none of its {record.requests} requests; its first refusal: " \
                     f"{record.first_refusal}"
        print(f"flextrack track: nothing scored: {reason}", file=sys.stderr)
        return 1
    return 0
