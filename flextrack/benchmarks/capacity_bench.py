"""`flextrack bench capacity`: how many 30 FPS devices one server holds with p99 under a bound, against
a no-op echo servicer in the same run, and what the server does at twice that load.

For each backend (the echo servicer, then each estimator of a `flextrack serve` process) the load
generator (flextrack.loadtest.ramp) searches the largest client count whose p99 stays under the bound. Then
the estimator's server, now started with `--max-streams` under that capacity (as an operator
would set it from this figure), gets twice its capacity, one connection per device: it must stay
up, refuse the excess devices at once with RESOURCE_EXHAUSTED (they wait as its retry pushback
asks, as the SDK does) and keep the accepted frames' p99 bounded. `--max-queue` bounds each
estimator's frame queue besides.

`--cpu-cost DEVICES` measures instead of searching, for a machine shared with other work, where a
ramp's p99 says more about the neighbours than about the server: each backend's server gets a fixed
offered load (DEVICES devices at --fps, well under what it holds), and its process's CPU seconds
(user + system, /proc) over its OK answers, less what it burns idle (measured just before, without
load: gRPC's pollers, health), give its CPU a frame, gRPC and the event loop included. Devices per
core at --fps = (1 - idle share) / (fps x CPU a frame), the bound a core gives before any
queueing; the p50/p99 at that offered load are measured beside it. The backends take turns in rounds, like
the ramps, and each figure is the median over the rounds.

`--tracking` sends the estimators' frames as a tracking device does: each with its prior (the
sequence's true pose perturbed by a seeded draw of a 1 deg / 5 mm covariance, which it carries) and
cut to the SDK's crop around it (client_sdk.crop), with 10 kB of tracker state: what `pvnet_region`
(region on every frame) gets from devices that track.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

from flextrack.loadtest import front_proxy, ramp, report, runner, servers, workload
from flextrack.provenance import of_args


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", type=Path,
                        help="server config (TOML); default: gt_oracle on a generated toy sequence")
    parser.add_argument("--sequence", type=Path, help="sequence folder the clients send (needed with --config)")
    parser.add_argument("--estimators", default="gt_oracle", help="comma-separated estimator names to measure")
    parser.add_argument("--fps", type=float, default=30.0, help="each device's frame rate, Hz (default: %(default)g)")
    parser.add_argument("--payload-kb", type=float, default=100.0, help="request size, kB (default: %(default)g)")
    parser.add_argument("--p99-bound-ms", type=float, default=50.0,
                        help="a device count is held while its p99 latency stays under this, ms (default: %(default)g)")
    parser.add_argument("--step-s", type=float, default=4.0, help="measured seconds per ramp step")
    parser.add_argument("--start-clients", type=int, default=4, help="devices at the ramp's first step (default: %(default)s)")
    parser.add_argument("--max-clients", type=int, default=512, help="the ramp stops here (default: %(default)s)")
    parser.add_argument("--channels", type=int, default=1, help="client channels (0 = one per client)")
    parser.add_argument("--max-queue", type=int, default=8, help="admission bound of the server (--max-queue)")
    parser.add_argument("--workers", type=int, default=4, help="estimator threads of the server (--workers)")
    parser.add_argument("--serve-arg", action="append", default=[], help="extra argument for `flextrack serve`")
    parser.add_argument("--repeats", type=int, default=3, help="ramp rounds per backend (median reported)")
    parser.add_argument("--stream-headroom", type=float, default=0.6,
                        help="overload run: --max-streams = this share of the measured capacity (0.6 leaves the "
                             "event loop the idle time to refuse the rest within a few ms; docs/operations.md)")
    parser.add_argument("--no-overload", action="store_true", help="skip the run at twice the capacity")
    parser.add_argument("--capacity", type=int,
                        help="skip the ramps and take this as the capacity (overload run only, e.g. to compare "
                             "server settings at the capacity an earlier run measured)")
    parser.add_argument("--server-cpus", help="pin each server process to these CPUs, e.g. 1 (default: no pinning)")
    parser.add_argument("--client-cpus", help="pin the load generator to these CPUs, e.g. 0: on a small machine "
                        "a load generator sharing the server's cores takes CPU from it, and its own timings suffer")
    parser.add_argument("--front", choices=("none", "nginx"), default="none",
                        help="nginx: every server behind an nginx (flextrack/loadtest/front_proxy.py) that counts open Track "
                        "streams and refuses the excess itself, before the Python process; the server keeps a "
                        "looser --max-streams as a backstop")
    parser.add_argument("--front-cpus", help="pin the front proxy to these CPUs (default: --server-cpus)")
    parser.add_argument("--front-nice", type=int, default=0,
                        help="the front proxy's nice value; below 0 (root only) it runs ahead of a server on its CPU")
    parser.add_argument("--probe-nice", type=int, default=0,
                        help="the lone probe device's nice value; below 0 (root only) it runs ahead of the load "
                        "generator it shares a CPU with, as a phone has its own")
    parser.add_argument("--tracking", action="store_true",
                        help="the estimators' frames as a tracking device sends them: with a prior and cut to the "
                             "SDK's crop around it (needs --sequence with rendered frames and ground truth)")
    parser.add_argument("--cpu-cost", type=int, metavar="DEVICES",
                        help="instead of the ramps and the overload run: offer DEVICES devices at --fps to each "
                             "backend for --step-s seconds per round and derive devices per core from the server's "
                             "CPU a frame (for a shared machine)")
    parser.add_argument("--out", type=Path, default=Path("out/bench_capacity"),
                        help="folder for capacity.json and the servers' logs (default: %(default)s)")


def _toy_config(tmp: Path) -> tuple[Path, Path]:
    from flextrack.testing.toy_sequence import write_orbit_sequence

    seq = write_orbit_sequence(tmp / "orbit", frames=300)
    config = tmp / "capacity.toml"
    config.write_text(f'[server]\ndefault_estimator = "gt_oracle"\n\n[[estimators]]\nname = "gt_oracle"\n'
                      f'kind = "gt_oracle"\n[estimators.params]\nsequence_roots = ["{seq.root}"]\n')
    return config, seq.root


TRACKING_STATE_BYTES = 10 * 1024  # the tracker state a device sends with each frame (client_state)
PRIOR_STD_DEG, PRIOR_STD_M = 1.0, 0.005


def _tracking_workload(root: Path, estimator: str, max_frames: int = 60, seed: int = 0) -> workload.Workload:
    """Frames of a rendered sequence as a tracking device sends them: the prior, the crop around it, the state."""
    import cv2
    import numpy as np

    from client_sdk.crop import crop_rect
    from flextrack import wire
    from flextrack.formats import sequence as sequence_io
    from flextrack.geometry import se3, so3
    from flextrack.geometry.camera import bbox_corners
    from flextrack.runners.payload import frame_jpeg
    from flextrack.runners.session import model_vertices
    from flextrack.v1 import pose_estimation_pb2 as pb

    seq = sequence_io.load(root)
    corners = bbox_corners(model_vertices(seq))
    cov = wire.diagonal_covariance(np.radians(PRIOR_STD_DEG), PRIOR_STD_M)
    rng = np.random.default_rng(seed)
    templates = []
    for frame_id, t_ns in list(zip(seq.frame_ids, seq.frame_times_ns))[:max_frames]:
        T_gt, path = seq.gt_T_CO.get(int(frame_id)), seq.rgb_path(int(frame_id))
        if T_gt is None or not path.exists():
            continue
        e = rng.multivariate_normal(np.zeros(6), cov)
        T_prior = se3.make(so3.exp(e[:3]) @ T_gt[:3, :3], T_gt[:3, 3] + e[3:])
        rgb = cv2.imread(str(path), cv2.IMREAD_COLOR)[:, :, ::-1]
        x, y, w, h = crop_rect(seq.camera, corners, T_prior, cov) or (0, 0, seq.camera.width, seq.camera.height)
        req = pb.EstimateRequest(
            estimator=estimator, capture_time_ns=int(t_ns), object_id=seq.object_id, sequence=seq.name,
            intrinsics=wire.intrinsics_to_pb(seq.camera), crop=pb.Crop(x=x, y=y, width=w, height=h),
            image=pb.Image(encoding=pb.Image.JPEG, data=frame_jpeg(rgb[y:y + h, x:x + w]), width=w, height=h),
            prior=pb.PosePrior(pose=wire.pose_to_pb(T_prior), covariance=wire.covariance_to_pb(cov)),
            client_state=rng.bytes(TRACKING_STATE_BYTES))
        templates.append(workload.FrameTemplate(req.capture_time_ns, req.SerializeToString()))
    if not templates:
        raise ValueError(f"{root}: no rendered frames with ground truth (simulate it with --render)")
    return workload.Workload(templates)


def _ramp(name: str, spec: runner.LoadSpec, work: workload.Workload, args, out: Path) -> dict:
    print(f"{name}: ramp at {args.fps:g} FPS, p99 bound {args.p99_bound_ms:g} ms", flush=True)

    def show(step: ramp.RampStep) -> None:
        lat = step.summary["latency_all"]
        print(f"  {step.clients:4d} clients: {step.summary['ok_fps']:7.0f} OK/s, p50 {lat['p50_ms'] or 0:6.1f} "
              f"p99 {lat['p99_ms'] or 0:7.1f} ms, errors {step.summary['error_rate']:.1%} "
              f"{'pass' if step.passed else 'FAIL'}", flush=True)

    best, steps = ramp.ramp(spec, work, args.p99_bound_ms, 0.01, args.start_clients, args.max_clients, show)
    ramp.write_ramp(steps, best, args.p99_bound_ms, out / name)
    at_best = next((s.summary for s in steps if s.clients == best), None)
    return {"capacity_clients": best, "ok_fps_at_capacity": at_best["ok_fps"] if at_best else 0.0,
            "p99_ms_at_capacity": at_best["latency_all"]["p99_ms"] if at_best else None}


def _overload(name: str, spec: runner.LoadSpec, work: workload.Workload, clients: int, server, out: Path,
              probe_cpus: set[int] | None = None, probe_nice: int = 0) -> dict:
    # A lone probe process times refusals as one device sees them, apart from the load generator's loop.
    probe = subprocess.Popen([sys.executable, "-m", "flextrack.benchmarks.refusal_probe", spec.targets[0],
                              str(spec.warmup_s + spec.duration_s)], stdout=subprocess.PIPE, text=True)
    servers.pin(probe.pid, probe_cpus)
    if probe_nice:
        os.setpriority(os.PRIO_PROCESS, probe.pid, probe_nice)
    result = runner.run(replace(spec, clients=clients), work)
    probed = json.loads(probe.communicate(timeout=30)[0] or "{}")
    probe_ms = report.percentiles(probed.get("refused_ms", []))
    summary = report.write_all(result, out / name, stem="overload")
    refused = [s.latency_ms for s in result.samples if s.outcome == "grpc:RESOURCE_EXHAUSTED"]
    print(f"{name}: overload at {clients} clients\n{report.format_summary(summary)}", flush=True)
    shown = "/".join("-" if probe_ms[k] is None else f"{probe_ms[k]:.1f}" for k in ("p50_ms", "p99_ms", "max_ms"))
    print(f"  lone probe device: {len(probed.get('refused_ms', []))} refusals, p50/p99/max {shown} ms, "
          f"{probed.get('admitted')} admitted", flush=True)
    try:
        servers.wait_serving(server.address, timeout_s=5, process=server.process)
        up = True
    except (RuntimeError, TimeoutError):
        up = False
    return {"clients": clients, "server_up_after": up, "ok_fps": summary["ok_fps"],
            "ok_p99_ms": summary["latency_ok"]["p99_ms"], "rejected_p99_ms": summary["latency_rejected"]["p99_ms"],
            "rejected_max_ms": max(refused) if refused else None,
            "probe_refused_ms": probe_ms, "probe_admitted": probed.get("admitted"),
            "rejected_share": 1 - summary["outcomes"].get("OK", 0) / max(1, summary["answered"]),
            "outcomes": summary["outcomes"]}


def _cpu_cost(names: list[str], works: dict, serve_args: list[str], base: runner.LoadSpec, server_cpus,
              args, out: Path) -> dict:
    """Per backend, its server's CPU a frame at a fixed offered load, devices per core from it, and the latency
    there; the median over `args.repeats` rounds, the backends in alternating order."""
    from flextrack.benchmarks.service_bench import _cpu_s

    running = {"echo": servers.start_echo(cpus=server_cpus)}
    rounds: dict[str, list[dict]] = {}
    try:
        for n in names:
            running[n] = servers.start_serve(serve_args, n, log_path=out / f"{n}_server.log", cpus=server_cpus)
        rounds = {n: [] for n in running}
        spec = replace(base, clients=args.cpu_cost, warmup_s=0.0)
        for n, server in running.items():  # warm-up: connections, the estimators' first frames
            runner.run(replace(spec, targets=(server.address,), duration_s=1.0), works[n])
        for r in range(args.repeats):
            for n in (list(running) if r % 2 == 0 else list(running)[::-1]):
                server = running[n]
                idle_s = min(2.0, args.step_s)
                cpu0, t0 = _cpu_s(server.process.pid), time.perf_counter()
                time.sleep(idle_s)
                idle = (_cpu_s(server.process.pid) - cpu0) / (time.perf_counter() - t0)  # CPU s a second, no load
                cpu0, t0 = _cpu_s(server.process.pid), time.perf_counter()
                result = runner.run(replace(spec, targets=(server.address,)), works[n])
                cpu, wall = _cpu_s(server.process.pid) - cpu0, time.perf_counter() - t0
                summary = report.summarize(result)
                # per OK answer: a refusal's little CPU is charged to the frames answered
                answered = max(1, summary["outcomes"].get("OK", 0))
                entry = {"cpu_ms_per_frame": 1e3 * max(cpu - idle * wall, 0.0) / answered,
                         "gross_cpu_ms_per_frame": 1e3 * cpu / answered, "idle_cpu_share": idle,
                         "answered": summary["answered"],
                         "ok_fps": summary["ok_fps"], "offered_fps": summary["offered_fps"],
                         "error_rate": summary["error_rate"], "skipped_frames": summary["skipped_frames"],
                         "latency_ms": summary["latency_all"], "load_average": os.getloadavg()[0]}
                entry["devices_per_core"] = (1.0 - idle) * 1e3 / (args.fps * max(entry["cpu_ms_per_frame"], 1e-6))
                rounds[n].append(entry)
                lat = entry["latency_ms"]
                print(f"  {n}: {entry['cpu_ms_per_frame']:.2f} ms CPU a frame (idle {100 * idle:.1f} % of a core; "
                      f"{entry['devices_per_core']:.1f} devices "
                      f"per core at {args.fps:g} FPS), p50 {lat['p50_ms'] or 0:.1f} p99 {lat['p99_ms'] or 0:.1f} ms, "
                      f"errors {entry['error_rate']:.1%}, load {entry['load_average']:.1f}", flush=True)
    finally:
        exit_codes = {n: server.stop() for n, server in running.items()}
    backends = {}
    for n, entries in rounds.items():
        entries = sorted(entries, key=lambda e: e["cpu_ms_per_frame"])
        backends[n] = dict(entries[len(entries) // 2], rounds_cpu_ms=[e["cpu_ms_per_frame"] for e in entries],
                           exit_code=exit_codes[n])
    return backends


def _print_cpu_cost(backends: dict, devices: int, fps: float, p99_bound_ms: float) -> None:
    print(f"\n{'backend':<14}{'CPU ms/frame':>13}{'devices/core':>14}{'p50 ms':>8}{'p99 ms':>8}{'errors':>8}"
          f"   at {devices} devices x {fps:g} FPS (median of the rounds)")
    for name, e in backends.items():
        p99 = e["latency_ms"]["p99_ms"]
        flag = "" if p99 is not None and p99 < p99_bound_ms else f"  (p99 not under {p99_bound_ms:g} ms)"
        print(f"{name:<14}{e['cpu_ms_per_frame']:>13.2f}{e['devices_per_core']:>14.1f}"
              f"{e['latency_ms']['p50_ms'] or 0:>8.1f}{p99 or 0:>8.1f}{e['error_rate']:>8.1%}{flag}")


def _ramps(names: list[str], works: dict, serve_args: list[str], base: runner.LoadSpec, server_cpus, front_cpus,
           args, out: Path) -> dict:
    """Each backend's capacity: the echo servicer's and each estimator's, the median over `args.repeats` rounds."""
    running = {"echo": servers.start_echo(cpus=server_cpus)}
    fronts = []
    try:
        for n in names:
            running[n] = servers.start_serve(serve_args, n, log_path=out / f"{n}_server.log", cpus=server_cpus)
        if args.front == "nginx":  # the same path as the overload run's, without a bound
            for n, server in running.items():
                fronts.append(front_proxy.start_nginx(server.address, None, out / f"nginx_{n}", front_cpus,
                                                      args.front_nice))
                running[n] = servers.ServerProcess(n, fronts[-1].address, server.process)
        # Rounds alternate the order of the backends, so that load from elsewhere on the machine falls
        # on all of them alike; each backend's figure is the median over the rounds.
        rounds: dict[str, list[dict]] = {n: [] for n in running}
        for r in range(args.repeats):
            for n in (list(running) if r % 2 == 0 else list(running)[::-1]):
                spec = replace(base, targets=(running[n].address,))
                rounds[n].append(_ramp(n, spec, works[n], args, out / f"round{r}"))
    finally:
        for proxy in fronts:
            proxy.stop()
        exit_codes = {n: server.stop() for n, server in running.items()}
    backends = {}
    for n, entries in rounds.items():
        entries.sort(key=lambda e: e["capacity_clients"])
        backends[n] = dict(entries[len(entries) // 2], rounds=[e["capacity_clients"] for e in entries],
                           exit_code=exit_codes[n])
    return backends


def run(args: argparse.Namespace) -> int:
    if args.cpu_cost is not None and args.cpu_cost < 1:
        print(f"flextrack bench capacity: --cpu-cost must be at least 1 device, got {args.cpu_cost}", file=sys.stderr)
        return 2
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    results: dict = {"date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "fps": args.fps,
                     "payload_kb": args.payload_kb, "p99_bound_ms": args.p99_bound_ms, "front": args.front,
                     "backends": {}}
    try:
        server_cpus, client_cpus = servers.parse_cpus(args.server_cpus), servers.parse_cpus(args.client_cpus)
        front_cpus = servers.parse_cpus(args.front_cpus) if args.front_cpus else server_cpus
    except ValueError as exc:
        print(f"flextrack bench capacity: {exc}")
        return 2
    servers.pin(0, client_cpus)
    results["server_cpus"], results["client_cpus"] = args.server_cpus, args.client_cpus
    results["front_cpus"] = args.front_cpus or args.server_cpus
    with tempfile.TemporaryDirectory() as tmp:
        config, sequence = (args.config, args.sequence) if args.config else _toy_config(Path(tmp))
        if sequence is None:
            print("flextrack bench capacity: --config needs --sequence (the frames the clients send)")
            return 2
        base = runner.LoadSpec(("127.0.0.1:1",), 1, args.fps, args.step_s, 1.0, channels=args.channels)
        serve_args = ["--config", str(config), "--max-queue", str(args.max_queue), "--workers", str(args.workers),
                      "--log-level", "WARNING", *args.serve_arg]
        names = [n for n in args.estimators.split(",") if n]
        frames = (lambda n: _tracking_workload(sequence, n)) if args.tracking else \
            (lambda n: workload.from_sequence(sequence, args.payload_kb, n))
        try:
            works = {"echo": workload.synthetic(args.payload_kb, fps=args.fps), **{n: frames(n) for n in names}}
        except (ValueError, FileNotFoundError) as exc:
            print(f"flextrack bench capacity: {exc}")
            return 2
        results["request_kb"] = {n: w.request_bytes / 1024 for n, w in works.items()}
        if args.cpu_cost:
            results["cpu_cost"] = {"devices": args.cpu_cost, "seconds": args.step_s, "tracking": args.tracking,
                                   "backends": _cpu_cost(names, works, serve_args, base, server_cpus, args, out)}
            _print_cpu_cost(results["cpu_cost"]["backends"], args.cpu_cost, args.fps, args.p99_bound_ms)
            results["provenance"] = of_args(args, command="flextrack bench capacity")
            (out / "capacity.json").write_text(json.dumps(results, indent=2))
            print(f"wrote {out}/capacity.json")
            return 0
        if args.capacity:
            results["backends"] = {n: {"capacity_clients": args.capacity, "given": True} for n in names}
        else:
            results["backends"] = _ramps(names, works, serve_args, base, server_cpus, front_cpus, args, out)
        for n in ([] if args.no_overload else names):
            # The operator's setting from this figure: under `capacity` devices per replica, so that
            # the event loop keeps the headroom to refuse the rest at once.
            capacity = max(1, results["backends"][n]["capacity_clients"])
            max_streams = max(1, int(args.stream_headroom * capacity))
            # behind nginx, the server's own bound is a looser backstop: a stream nginx has just closed
            # may still be open on the server for a moment
            server_bound = max_streams + max(2, max_streams // 4) if args.front == "nginx" else max_streams
            server = servers.start_serve([*serve_args, "--max-streams", str(server_bound)], n,
                                         log_path=out / f"{n}_server.log", cpus=server_cpus)
            proxy = None
            overload = {}
            try:
                if args.front == "nginx":
                    proxy = front_proxy.start_nginx(server.address, max_streams, out / f"nginx_{n}", front_cpus,
                                                    args.front_nice)
                gate = proxy or server
                # one connection per device, as phones have: on a shared connection a refusal waits behind
                # the other devices' frames
                spec = replace(base, targets=(gate.address,), await_admission=True, channels=0)
                overload = _overload(n, spec, works[n], 2 * capacity, server, out, client_cpus, args.probe_nice)
            finally:
                if proxy is not None:
                    proxy.stop()
                overload["exit_code"] = server.stop()
            results["backends"][n]["overload"] = dict(overload, max_streams=max_streams, front=args.front)
    if not args.capacity:
        _print_against_echo(results["backends"], args.p99_bound_ms)
    results["provenance"] = of_args(args, command="flextrack bench capacity")
    (out / "capacity.json").write_text(json.dumps(results, indent=2))
    print(f"wrote {out}/capacity.json" + (" (capacity given: no ramps)" if args.capacity else " and a ramp per backend"))
    return 0


def _print_against_echo(backends: dict, p99_bound_ms: float) -> None:
    echo_fps = backends["echo"]["ok_fps_at_capacity"] or float("nan")
    print(f"\n{'backend':<12}{'clients@p99<' + format(p99_bound_ms, 'g') + 'ms':>20}{'rounds':>16}{'OK/s':>9}"
          f"{'vs echo':>9}")
    for name, entry in backends.items():
        entry["fps_vs_echo"] = entry["ok_fps_at_capacity"] / echo_fps
        print(f"{name:<12}{entry['capacity_clients']:>20}{entry['rounds']!s:>16}{entry['ok_fps_at_capacity']:>9.0f}"
              f"{entry['fps_vs_echo']:>9.2f}")
