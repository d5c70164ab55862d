"""A stand-in for the paper's 90 kB frame when no image is rendered.

The paper sent a 640x480 JPEG of about 90 kB with every request. When a run renders no frames
(oracle backends never look at pixels) we still send a real, decodable JPEG of that size: a plain
grey image padded with APP15 segments of seeded random bytes, so the wire, the interceptor's
payload size and the server's image check all see what they would see with a rendered frame.
"""

from __future__ import annotations

import io
from functools import lru_cache

import numpy as np
from PIL import Image

PAPER_JPEG_BYTES = 90 * 1024  # a 640x480 JPEG at compression ratio 10 (paper Section 4.1)
_APP15 = b"\xff\xef"
_MAX_SEGMENT_DATA = 65533  # a segment's 2-byte length counts itself


@lru_cache(maxsize=8)
def _plain_jpeg(width: int, height: int) -> bytes:
    buf = io.BytesIO()
    Image.new("L", (width, height), 128).save(buf, format="JPEG", quality=50)
    return buf.getvalue()


def stand_in_jpeg(width: int = 640, height: int = 480, n_bytes: int = PAPER_JPEG_BYTES, seed: int = 0) -> bytes:
    """A valid width x height JPEG of `n_bytes` (to 3 bytes; never below its minimum size)."""
    base = _plain_jpeg(int(width), int(height))
    pad = n_bytes - len(base)
    rng = np.random.default_rng(seed)
    segments = []
    while pad >= 4:
        data_len = min(_MAX_SEGMENT_DATA, pad - 4)
        if 0 < pad - 4 - data_len < 4:  # leave the last segment room for its own header
            data_len -= 4
        segments.append(_APP15 + (data_len + 2).to_bytes(2, "big") + rng.bytes(data_len))
        pad -= 4 + data_len
    return base[:2] + b"".join(segments) + base[2:]


CHROMA_SUBSAMPLING = {"444": 0, "420": 2}  # PIL's `subsampling` values


def frame_jpeg(rgb: np.ndarray, quality: int = 90, chroma: str = "444") -> bytes:
    """A camera frame as the device sends it: JPEG with full-resolution colour (4:4:4) by default.

    Why not JPEG's usual 4:2:0: it halves the colour resolution, which blurs and shifts edges that
    are colour rather than brightness (an object's outline against a background of like
    brightness) by about a pixel, and the pvnet estimator's refinement fits the pose to those
    edges: on 200 rendered tuning frames at quality 90, ADD < 10 % of the diameter was 74.5 % with
    4:2:0, 84.0 % with 4:4:4 and 87.0 % uncompressed (docs/pvnet.md). 4:4:4 costs 40 % more bytes:
    88 kB a 640x480 frame of the simulated room against 63 kB, about the paper's 90 kB."""
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb)).save(buf, format="JPEG", quality=int(quality),
                                                    subsampling=CHROMA_SUBSAMPLING[chroma])
    return buf.getvalue()


class RenderedJpegs:
    """JPEG bytes of a sequence's frames for image estimators (PVNet): rendered on demand by the
    simulator (and kept in the folder's rgb/), so a replay renders only the frames it sends."""

    def __init__(self, seq, quality: int = 90):
        from flextrack.simulator.frames import SequenceFrames  # the sim extra: only image runs need it

        self._frames = SequenceFrames(seq)
        self._quality = int(quality)

    def __call__(self, frame_id: int, crop=None) -> bytes:
        """The frame's JPEG, or that of `crop`'s rectangle of it (a `Crop`, client_sdk.crop)."""
        rgb = self._frames.frame(int(frame_id)).rgb
        if crop is not None:
            rgb = rgb[crop.y:crop.y + crop.height, crop.x:crop.x + crop.width]
        return frame_jpeg(rgb, self._quality)

    def close(self) -> None:
        self._frames.close()
