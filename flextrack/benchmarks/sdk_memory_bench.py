"""`flextrack bench sdk-memory`: the client's memory over a long live session.

`--runner sdk` (the default): a device runs the SDK alone (tracker core, `TrackClient`, the latency
interceptor in live mode) in real time against a `flextrack serve` child process with the
ground-truth oracle, on a simulated sequence as long as the run; nothing is recorded for scoring.
`--runner track-live`: what `flextrack track --live` runs (flextrack.runners.live, its record for
scoring included) against the same server. Every `--sample-s` it prints the process's RSS once its
free heap pages are returned (`held_mib`; and for the SDK, the sizes of its buffers); at the end, the
slope after the first minute, which is what an hour-long AR session would add.
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import queue
import tempfile
import time
from pathlib import Path

import numpy as np

from flextrack.provenance import of_args
from flextrack.runners.cli_checks import deprecated_alias


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--duration", type=float, default=300.0, help="length of the live run, s")
    deprecated_alias(parser, "--duration-s", "--duration", type=float)
    parser.add_argument("--fps", type=float, default=60.0, help="camera frame rate")
    parser.add_argument("--sample-s", type=float, default=10.0, help="seconds between two RSS samples")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tracker", choices=["filter", "paper"], default="filter",
                        help="the tracker core (TrackerOptions.fusion): the error-state filter or the paper's PRM")
    deprecated_alias(parser, "--fusion", "--tracker", choices=["filter", "paper"])
    parser.add_argument("--runner", choices=["sdk", "track-live"], default="sdk",
                        help="sdk: the SDK alone; track-live: the live runner of `flextrack track --live`, its record "
                             "for scoring included")
    parser.add_argument("--csv", type=Path, help="also write the samples here (and their provenance beside, .json)")


SETTLE_S = 60.0  # the slope is fitted after this: the first minute fills caches, buffers and the allocator


def held_mib() -> float:
    """The RSS once the process has returned its free heap pages (garbage collected, malloc_trim): what it holds.
    Without it a live run's RSS swung between levels 10-30 MB apart as glibc kept or returned the pages of
    transient arrays, and a fitted slope said more about when the samples fell than about growth."""
    _release_free_memory()
    return rss_mib()


def rss_mib() -> float:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _release_free_memory() -> None:
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)  # glibc keeps freed heap pages resident until asked
    except (OSError, AttributeError):
        pass


def sdk_buffers(tracker, client, interceptor) -> dict[str, int]:
    """What the SDK keeps per frame or per sample: each must stay bounded however long the session."""
    return {"imu_buffer": len(tracker._buf), "in_flight": client.in_flight,
            "uplinks": len(interceptor._uplinks), "stamps": len(interceptor.stamps)}


def run(args: argparse.Namespace) -> int:
    from flextrack.formats import sequence as sequence_io
    from flextrack.loadtest.servers import start_serve
    from flextrack.simulator.generate import generate_sequence

    with tempfile.TemporaryDirectory() as tmp:
        root = generate_sequence("circular", "medium", Path(tmp) / "long", duration_s=args.duration,
                                 fps=args.fps, seed=args.seed)
        seq = sequence_io.load(root)
        _release_free_memory()  # the simulation's temporaries: not the SDK's, out of the baseline
        config = Path(tmp) / "server.toml"
        config.write_text(f'[[estimators]]\nname = "gt"\nkind = "gt_oracle"\n[estimators.params]\n'
                          f'sequence_roots = ["{root}"]\n')
        server = start_serve(["--config", str(config)])
        try:
            run_device = _device if args.runner == "sdk" else _track_live
            samples = run_device(seq, server.address, args.sample_s, args.tracker)
        finally:
            server.stop()
    later = [s for s in samples if s["t_s"] >= SETTLE_S]
    slope = np.polyfit([s["t_s"] for s in later], [s["rss_mib"] for s in later], 1)[0] * 60 if len(later) > 1 else 0.0
    frames = samples[-1]["frames"]
    print(f"\n{frames} frames in {samples[-1]['t_s']:.0f} s: RSS {samples[0]['rss_mib']:.1f} -> "
          f"{samples[-1]['rss_mib']:.1f} MiB; after the first {SETTLE_S:.0f} s: {slope:+.3f} MiB/min "
          f"({slope * 1024 / 60 / args.fps * 1024:+.0f} B/frame)")
    if args.csv:
        keys = list(samples[0])
        args.csv.write_text(",".join(keys) + "\n" + "".join(",".join(str(s[k]) for k in keys) + "\n"
                                                          for s in samples))
        args.csv.with_suffix(".json").write_text(json.dumps({  # the CSV's provenance, beside it
            "provenance": of_args(args, command="flextrack bench sdk-memory"), "files": [args.csv.name]}, indent=1))
    return 0


def _device(seq, address: str, sample_s: float, fusion: str) -> list[dict]:
    """The device's loop in real time; returns the samples it printed."""
    from client_sdk import TrackerOptions, create_tracker
    from client_sdk.interceptor import LatencyInterceptor
    from client_sdk.transport import TrackClient, make_request
    from flextrack import wire
    from flextrack.geometry.camera import bbox_corners
    from flextrack.runners.payload import stand_in_jpeg
    from flextrack.runners.session import model_vertices
    from flextrack.v1 import pose_estimation_pb2 as pb

    tracker = create_tracker(TrackerOptions(fusion=fusion), seq.camera, seq.T_BC, bbox_corners(model_vertices(seq)))
    print(f"tracker core: {type(tracker).__name__}")
    image = stand_in_jpeg(seq.camera.width, seq.camera.height)
    interceptor = LatencyInterceptor(live=True)
    inbox: queue.Queue = queue.Queue()
    client = TrackClient(address, on_response=inbox.put, on_failure=lambda frame_id, why: inbox.put(frame_id),
                         interceptors=[interceptor])
    cam = seq.camera
    intrinsics = wire.intrinsics_to_pb(cam)
    events = sorted([(int(t), 0, i) for i, t in enumerate(seq.imu.t_ns)]
                    + [(int(t), 1, i) for i, t in enumerate(seq.frame_times_ns)])
    requests: dict[int, int] = {}  # frame id -> the tracker's request id
    samples, frames = [], 0
    print("t_s,frames,rss_mib,imu_buffer,in_flight,uplinks,stamps")
    with client:
        client.wait_connected(10.0)
        start, t0 = time.perf_counter(), events[0][0]
        next_sample = start
        for t_ns, kind, i in events:
            due = start + (t_ns - t0) * 1e-9
            while True:
                try:
                    answer = inbox.get(timeout=max(0.0, due - time.perf_counter()))
                except queue.Empty:
                    break
                frame_id = answer.frame_id if isinstance(answer, pb.EstimateResponse) else answer
                request_id = requests.pop(frame_id, None)
                if request_id is None:
                    continue
                if isinstance(answer, pb.EstimateResponse) and answer.status == pb.EstimateResponse.OK:
                    tracker.on_backend_response(request_id, answer.capture_time_ns, wire.pose_from_pb(answer.pose),
                                                True)
                else:
                    tracker.on_backend_failure(request_id)
            if kind == 0:
                tracker.add_imu(t_ns, seq.imu.gyro[i], seq.imu.accel[i])
                continue
            frames += 1
            result = tracker.add_frame(t_ns)
            if result.request is not None:
                frame_id = int(seq.frame_ids[i])
                requests[frame_id] = result.request.request_id
                sent = client.submit(make_request(
                    frame_id=frame_id, capture_time_ns=result.request.frame_t_ns, sequence=seq.name,
                    object_id=seq.object_id, image=image, width=cam.width, height=cam.height,
                    intrinsics=intrinsics, client_state=tracker.state_bytes()))
                if not sent and requests.pop(frame_id, None) is not None:
                    tracker.on_backend_failure(result.request.request_id)
            if time.perf_counter() >= next_sample:
                next_sample += sample_s
                sample = {"t_s": round(time.perf_counter() - start, 1), "frames": frames, "rss_mib": round(held_mib(), 2),
                          **sdk_buffers(tracker, client, interceptor)}
                samples.append(sample)
                print(",".join(str(v) for v in sample.values()), flush=True)
    return samples


def _track_live(seq, address: str, sample_s: float, fusion: str) -> list[dict]:
    """`flextrack track --live`'s runner against the server at `address`; returns the samples it printed."""
    from client_sdk import TrackerOptions
    from flextrack.runners.live import LiveOptions, run_live
    from flextrack.runners.session import model_vertices

    samples: list[dict] = []
    start = time.perf_counter()
    print("t_s,frames,rss_mib")

    def sample(p) -> None:
        sample = {"t_s": round(time.perf_counter() - start, 1), "frames": len(p.record.rows),
                  "rss_mib": round(held_mib(), 2)}
        samples.append(sample)
        print(",".join(str(v) for v in sample.values()), flush=True)

    run_live(seq, address, model_vertices(seq), TrackerOptions(fusion=fusion), LiveOptions(), progress=sample,
             progress_every_s=sample_s)
    return samples
