"""`flextrack bench jpeg-bound`: what the service's JPEG checks leave a frame's decode costing at worst.

A progressive JPEG's decode cost grows with its scans, not its bytes or pixels: each scan is one more
pass over every block of the frame (service.request_decoding.MAX_JPEG_SCANS). For each frame size it
builds progressive JPEGs of noise (the costliest content per scan) whose last scan, an AC refinement
of the luma, is repeated: with its data (as many as fit the message limit, within the scan limit) and
truncated to a few bytes (the scan bomb's form: the decoder still walks every block), and times the
service's own decode (`decode_image`, CPU seconds of this one thread) of each, and the refusal of
the same bomb over the limit and of 200,000 scans under a 640x480 header (the issue's reproduction).
"""

from __future__ import annotations

import argparse
import io
import json
import statistics
import time
from pathlib import Path

import numpy as np

from flextrack.provenance import of_args

SIZES = ((640, 480), (2048, 2048))  # the normal frame and the default pixel limit
MESSAGE_BYTES = 8 * 1024 * 1024  # the server's default message limit (service.server.DEFAULT_MAX_MESSAGE_MB)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--repeat", type=int, default=3, help="decodes of each JPEG (the median is reported)")
    parser.add_argument("--seed", type=int, default=0, help="the noise image's seed")
    parser.add_argument("--json", type=Path, help="also write the figures and their provenance here")


def progressive_jpeg(width: int, height: int, seed: int = 0) -> bytes:
    """A progressive JPEG of RGB noise (libjpeg's progression script: 10 scans)."""
    from PIL import Image

    pixels = np.random.default_rng(seed).integers(0, 256, (height, width, 3), dtype=np.uint8)
    out = io.BytesIO()
    Image.fromarray(pixels).save(out, "JPEG", quality=95, progressive=True)
    return out.getvalue()


def scan_bomb(jpeg: bytes, extra_scans: int, scan_bytes: int | None = None) -> bytes:
    """`jpeg` (progressive) with its last scan repeated `extra_scans` more times before EOI, each repeat cut to
    its first `scan_bytes` bytes (None: whole). The header stays honest: the frame's own size and tables."""
    last, end = jpeg.rfind(b"\xff\xda"), jpeg.rfind(b"\xff\xd9")
    scan = jpeg[last:end] if scan_bytes is None else jpeg[last:last + scan_bytes]
    return jpeg[:end] + scan * extra_scans + jpeg[end:]


def _cpu_s(image, camera, repeat: int) -> tuple[float, str]:
    """Median CPU seconds of decoding `image` as the service does, and the outcome."""
    from estimators.base import InvalidInput
    from service.request_decoding import decode_image

    times, outcome = [], "decoded"
    for _ in range(repeat):
        start = time.process_time()
        try:
            decode_image(image, camera)
        except InvalidInput as exc:
            outcome = f"refused: {exc}"
        times.append(time.process_time() - start)
    return statistics.median(times), outcome


def run(args: argparse.Namespace) -> int:
    from flextrack.geometry.camera import PinholeCamera
    from flextrack.v1 import pose_estimation_pb2 as pb
    from service.request_decoding import MAX_JPEG_SCANS

    if args.repeat < 1:
        raise SystemExit("--repeat must be >= 1")
    rows = []
    for width, height in SIZES:
        camera = PinholeCamera(500.0, 500.0, width / 2, height / 2, width, height)
        jpeg = progressive_jpeg(width, height, args.seed)
        scans = jpeg.count(b"\xff\xda")
        last_scan = jpeg.rfind(b"\xff\xd9") - jpeg.rfind(b"\xff\xda")
        room = MAX_JPEG_SCANS - scans
        cases = {"plain progressive": jpeg,
                 "last scan repeated, whole": scan_bomb(jpeg, min(room, (MESSAGE_BYTES - len(jpeg)) // last_scan)),
                 "last scan repeated, 32 bytes each": scan_bomb(jpeg, room, 32),
                 "one scan over the limit": scan_bomb(jpeg, room + 1, 32)}
        if (width, height) == (640, 480):
            cases["200,000 scans (the issue's bomb)"] = scan_bomb(jpeg, 200_000, 32)
        for name, data in cases.items():
            image = pb.Image(encoding=pb.Image.JPEG, data=data, width=width, height=height)
            cpu_s, outcome = _cpu_s(image, camera, args.repeat)
            row = {"size": f"{width}x{height}", "case": name, "scans": data.count(b"\xff\xda"), "bytes": len(data),
                   "cpu_ms": round(cpu_s * 1e3, 2), "outcome": outcome[:60]}
            rows.append(row)
            print(f"{row['size']:>9}  {name:<36} {row['scans']:>7} scans {row['bytes'] / 1e6:6.2f} MB  "
                  f"{row['cpu_ms']:8.2f} ms CPU  {row['outcome']}", flush=True)
    if args.json:
        args.json.write_text(json.dumps({"provenance": of_args(args, command="flextrack bench jpeg-bound",
                                                               max_jpeg_scans=MAX_JPEG_SCANS),
                                         "rows": rows}, indent=1) + "\n")
    return 0
