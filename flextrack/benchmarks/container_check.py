"""`flextrack bench container`: build the Dockerfile for real and check the image serves.

1. `container-check build` (podman, chroot isolation, a local Debian base passed as BASE_IMAGE;
   ../shared/tools/container-check) builds the repository's Dockerfile.
2. `container-check run -- ...` starts `flextrack serve` in the image (host network) with the
   oracle on a small sequence written inside the container.
3. From the host: the gRPC health service must say SERVING, and one Estimate must return the
   sequence's ground-truth pose.
4. A SIGTERM to container-check stops it (the tool ends the process tree in the image).

Too slow for every test run (the build takes minutes), so it is a benchmark-style command; its last
result is written to `--record` (docs/container_check.md).
"""

from __future__ import annotations

import argparse
import subprocess
import tempfile
import time
from pathlib import Path

import grpc
import numpy as np

from flextrack.loadtest import servers
from flextrack.provenance import provenance

REPO = Path(__file__).resolve().parents[2]
TOOL = REPO.parent / "shared" / "tools" / "container-check"
IN_CONTAINER = (
    "python3 -c \"from flextrack.testing.toy_sequence import write_orbit_sequence; "
    "write_orbit_sequence('/tmp/check/orbit', frames=30); "
    "open('/tmp/check/check.toml', 'w').write('[[estimators]]\\nname = \\\"gt_oracle\\\"\\nkind = \\\"gt_oracle\\\"\\n"
    "[estimators.params]\\nsequence_roots = [\\\"/tmp/check/orbit\\\"]\\n')\" "
    "&& exec flextrack serve --host 127.0.0.1 --port {port} --config /tmp/check/check.toml")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--tool", type=Path, default=TOOL, help="the container-check script")
    parser.add_argument("--skip-build", action="store_true", help="use the image of the last build")
    parser.add_argument("--timeout-s", type=float, default=180.0, help="how long the server may take to serve")
    parser.add_argument("--record", type=Path, help="write the result here as Markdown (e.g. docs/container_check.md)")
    parser.add_argument("--log", type=Path, default=Path("out/container_check.log"), help="build and run output")


def _estimate_matches_ground_truth(address: str) -> tuple[bool, str]:
    """One oracle request from the host; the pose must be the toy sequence's ground truth."""
    from flextrack import wire
    from flextrack.testing.toy_sequence import write_orbit_sequence
    from flextrack.v1 import pose_estimation_pb2 as pb
    from flextrack.v1 import pose_estimation_pb2_grpc as pb_grpc

    with tempfile.TemporaryDirectory() as tmp:
        seq = write_orbit_sequence(Path(tmp) / "orbit", frames=30)  # the same one the container wrote
    frame = 3
    with grpc.insecure_channel(address) as channel:
        reply = pb_grpc.PoseEstimationStub(channel).Estimate(
            pb.EstimateRequest(frame_id=frame, capture_time_ns=int(seq.frame_times_ns[frame]), sequence="orbit"),
            timeout=10)
    if reply.status != pb.EstimateResponse.OK:
        return False, f"status {pb.EstimateResponse.Status.Name(reply.status)}: {reply.message}"
    T = wire.pose_from_pb(reply.pose)
    error_m = float(np.linalg.norm(T[:3, 3] - seq.gt_T_CO[frame][:3, 3]))
    return error_m < 1e-6, f"OK from {reply.estimator}, translation error {error_m:.1e} m"


def run(args: argparse.Namespace) -> int:
    args.log.parent.mkdir(parents=True, exist_ok=True)
    steps: list[tuple[str, bool, str]] = []
    started = time.time()
    with open(args.log, "w") as log:
        if not args.skip_build:
            t0 = time.monotonic()
            build = subprocess.run(["nice", "-n", "10", str(args.tool), "build", str(REPO)], stdout=log,
                                   stderr=subprocess.STDOUT, check=False)
            steps.append(("build", build.returncode == 0, f"exit {build.returncode} in {time.monotonic() - t0:.0f} s"))
        if all(ok for _, ok, _ in steps):
            port = servers.free_port()
            address = f"127.0.0.1:{port}"
            proc = subprocess.Popen([str(args.tool), "run", "--", "sh", "-c", IN_CONTAINER.format(port=port)],
                                    stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
            try:
                t0 = time.monotonic()
                servers.wait_serving(address, args.timeout_s, proc)
                steps.append(("health SERVING from the host", True, f"after {time.monotonic() - t0:.1f} s"))
                ok, detail = _estimate_matches_ground_truth(address)
                steps.append(("oracle Estimate from the host", ok, detail))
            except (RuntimeError, TimeoutError, grpc.RpcError) as exc:
                steps.append(("serve in the container", False, str(exc)))
            finally:
                if proc.poll() is None:
                    proc.terminate()  # container-check passes a TERM on to what runs inside
                    try:
                        proc.wait(30)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        proc.wait()
                # container-check ends what runs inside itself (it exits 143 on TERM): the image's process tree
                steps.append(("stopped by SIGTERM to container-check", proc.returncode in (0, 143),
                              f"exit {proc.returncode}"))
    passed = all(ok for _, ok, _ in steps)
    lines = [f"- {'PASS' if ok else 'FAIL'} {name}: {detail}" for name, ok, detail in steps]
    print("\n".join(lines))
    print(f"container check {'PASSED' if passed else 'FAILED'} (log: {args.log})")
    if args.record:
        when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(started))
        prov = provenance(command="flextrack bench container")
        where = (f"commit {(prov['commit'] or 'unknown')[:10]}{' (uncommitted changes)' if prov['dirty'] else ''}, "
                 f"host {prov['host']}")
        args.record.write_text(
            "# Container check: last result\n\nWritten by `flextrack bench container --record docs/container_check.md`"
            " (flextrack/benchmarks/container_check.py): builds the Dockerfile with `../shared/tools/container-check build` "
            "(podman, chroot isolation, local Debian bookworm base) and runs `flextrack serve` in the image.\n\n"
            f"Run: {when}, {where}, result: **{'PASS' if passed else 'FAIL'}**\n\n" + "\n".join(lines) + "\n")
    return 0 if passed else 1
