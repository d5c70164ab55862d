"""Simulator speed: `python -m flextrack.simulator.bench` prints it.

- seconds to generate a 30 s, 120 FPS sequence folder without frames (IMU 200 Hz, pixel2);
- milliseconds per rendered 640x480 frame, object only and in the room (scene mode, with mask).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def bench_generate(repeats: int = 3) -> float:
    from flextrack.simulator.generate import generate_sequence
    times = []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(repeats):
            start = time.perf_counter()
            generate_sequence("circular", "hard", Path(tmp) / f"s{i}", duration_s=30.0, fps=120.0, imu_rate=200.0)
            times.append(time.perf_counter() - start)
    return float(np.median(times))


def bench_render(frames: int = 60) -> tuple[float, float]:
    from flextrack.simulator.frames import SequenceFrames
    from flextrack.simulator.generate import generate_sequence
    from flextrack.simulator.render import Renderer
    with tempfile.TemporaryDirectory() as tmp:
        root = generate_sequence("circular", "hard", Path(tmp) / "r", duration_s=30.0, fps=120.0)
        with SequenceFrames(root) as seq_frames:
            ids = seq_frames.seq.frame_ids[:: max(1, len(seq_frames.seq.frame_ids) // frames)][:frames]
            seq_frames.render(int(ids[0]))  # GL context and textures
            start = time.perf_counter()
            for i in ids:
                seq_frames.render(int(i))
            scene_ms = 1000 * (time.perf_counter() - start) / len(ids)
            poses = [seq_frames.seq.gt_T_CO[int(i)] for i in ids]
        with Renderer() as renderer:
            renderer.render(poses[0])
            start = time.perf_counter()
            for T in poses:
                renderer.render(T)
            object_ms = 1000 * (time.perf_counter() - start) / len(poses)
    return object_ms, scene_ms


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60, help="frames to time per render mode")
    args = parser.parse_args(argv)
    print(f"generate 30 s @ 120 FPS, IMU 200 Hz, no frames: {bench_generate():.2f} s (median of 3)")
    object_ms, scene_ms = bench_render(args.frames)
    print(f"render 640x480 object only: {object_ms:.1f} ms/frame; in the room (rgb + mask + depth): "
          f"{scene_ms:.1f} ms/frame ({args.frames} frames)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
