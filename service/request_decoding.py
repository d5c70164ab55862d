"""Wire messages -> checked numpy values; every problem is an `InvalidInput` a person can act on."""

from __future__ import annotations

import io
import math

import numpy as np
from PIL import Image, UnidentifiedImageError

from estimators.base import InvalidInput
from flextrack import wire
from flextrack.geometry.camera import PinholeCamera
from flextrack.v1 import pose_estimation_pb2 as pb

DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)  # what OpenCV accepts
# What a real camera can have: anything outside is refused before an estimator's numerics meet it
MIN_FOCAL_PX, MAX_FOCAL_PX = 1.0, 1e5
MAX_DISTORTION = 1e4
_FORMATS = {pb.Image.JPEG: "JPEG", pb.Image.PNG: "PNG"}


def _finite(name: str, *values: float) -> None:
    if not all(map(math.isfinite, values)):
        raise InvalidInput(f"{name} must be finite numbers, got {list(values)}")


def decode_camera(intr: pb.Intrinsics) -> PinholeCamera | None:
    """The request's camera, or None when it carries no intrinsics at all."""
    fx, fy, cx, cy, width, height = intr.fx, intr.fy, intr.cx, intr.cy, intr.width, intr.height
    if len(intr.distortion) not in DISTORTION_LENGTHS:  # counted before anything walks (or formats) them
        raise InvalidInput(f"distortion needs one of {DISTORTION_LENGTHS} coefficients (OpenCV order), "
                           f"got {len(intr.distortion)}")
    distortion = tuple(intr.distortion)
    if not (fx or fy or cx or cy or width or height or distortion):
        return None
    _finite("intrinsics fx, fy, cx, cy", fx, fy, cx, cy)
    _finite("intrinsics distortion", *distortion)
    if not (MIN_FOCAL_PX <= fx <= MAX_FOCAL_PX and MIN_FOCAL_PX <= fy <= MAX_FOCAL_PX):
        raise InvalidInput(f"intrinsics fx and fy must be {MIN_FOCAL_PX:g}..{MAX_FOCAL_PX:g} px, got fx={fx}, fy={fy}")
    if width == 0 or height == 0:
        raise InvalidInput(f"intrinsics width and height must be positive, got {width}x{height}")
    if not (-width <= cx <= 2 * width and -height <= cy <= 2 * height):
        raise InvalidInput(f"intrinsics principal point ({cx}, {cy}) is far outside the {width}x{height} image")
    if any(abs(k) > MAX_DISTORTION for k in distortion):
        raise InvalidInput(f"distortion coefficients must be within +-{MAX_DISTORTION:g}")
    return PinholeCamera(fx, fy, cx, cy, width, height, distortion)


def decode_prior(request: pb.EstimateRequest) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(T_CO, covariance) of the request's prior: (None, None) when it has none; the covariance is None
    when the prior came without one (the estimator's documented default applies)."""
    if not request.HasField("prior"):
        return None, None
    prior = request.prior
    if not prior.HasField("pose"):
        raise InvalidInput("prior must carry a pose (T_CO at the capture time)")
    p = prior.pose
    q = np.array([p.qw, p.qx, p.qy, p.qz])
    _finite("prior pose", p.tx, p.ty, p.tz, *q)
    if abs(float(np.linalg.norm(q)) - 1.0) > 1e-3:
        raise InvalidInput(f"prior pose must be a rigid transform: its quaternion has norm {np.linalg.norm(q):.6g}, not 1")
    T = wire.pose_from_pb(p)
    if len(prior.covariance.data) not in (0, 36):  # counted before anything walks them
        raise InvalidInput(f"prior covariance must have 36 values (6x6 row-major) or none, "
                           f"got {len(prior.covariance.data)}")
    try:
        cov = wire.covariance_from_pb(prior.covariance, "prior covariance")
    except wire.BadCovariance as exc:
        raise InvalidInput(str(exc)) from None
    return T, cov


def decode_keypoints(keypoints) -> np.ndarray:
    """(N, 3) array of id, u, v."""
    if not keypoints:
        return np.zeros((0, 3))
    kp = np.array([(k.id, k.u, k.v) for k in keypoints], dtype=float).reshape(-1, 3)
    if not np.all(np.isfinite(kp)):
        raise InvalidInput("keypoint coordinates must be finite numbers")
    return kp



def decode_crop(request: pb.EstimateRequest, camera: PinholeCamera | None,
                keypoints: np.ndarray) -> tuple[PinholeCamera | None, np.ndarray]:
    """The camera and keypoints of the pixels the image holds: unchanged for a whole frame; for a crop
    (protos: `Crop`), the full frame's camera with its principal point moved by the crop's offset and
    its size the crop's, and the keypoints moved likewise. Every estimator then reads a crop as an
    image of its own, and its pose stays T_CO in the camera frame."""
    if not request.HasField("crop"):
        return camera, keypoints
    c = request.crop
    if not (c.x or c.y or c.width or c.height):
        return camera, keypoints
    if camera is None:
        raise InvalidInput("a crop needs the full frame's intrinsics (fx, fy, cx, cy, width, height)")
    if c.width == 0 or c.height == 0:
        raise InvalidInput(f"crop width and height must be positive, got {c.width}x{c.height}")
    if c.x + c.width > camera.width or c.y + c.height > camera.height:
        raise InvalidInput(f"crop {c.width}x{c.height} at ({c.x}, {c.y}) reaches past the {camera.width}x"
                           f"{camera.height} frame of the intrinsics")
    image = request.image
    if (image.width, image.height) != (c.width, c.height):
        raise InvalidInput(f"image is {image.width}x{image.height} but the crop is {c.width}x{c.height}: "
                           f"the image holds the crop")
    cropped = PinholeCamera(camera.fx, camera.fy, camera.cx - c.x, camera.cy - c.y, c.width, c.height,
                            camera.distortion)
    if len(keypoints):
        keypoints = keypoints - np.array([0.0, c.x, c.y])
    return cropped, keypoints

MAX_JPEG_SEGMENTS = 256  # before the first scan; real files have a dozen or two
MAX_JPEG_FILL_BYTES = 4096  # fill bytes (0xFF) before the first scan, which Pillow walks one by one in Python
# Scans (SOS markers) a decoded JPEG may hold. Each scan of a progressive JPEG is one more pass of libjpeg over
# every block of the frame, whatever few bytes it has: one AC scan repeated 200,000 times under a 640x480 header
# (6.8 MB) cost 21 s of CPU. Encoders write 1 (baseline), 3 (non-interleaved) or about 10 (libjpeg's and
# mozjpeg's progressive scripts); libjpeg-turbo's own guard is a scan limit (djpeg -maxscans, TJPARAM_SCANLIMIT),
# which Pillow does not expose, so the scans are counted before the decode (docs/operations.md: the bound).
MAX_JPEG_SCANS = 100


def _fill_end(data: bytes, i: int) -> int:
    """The index of the first byte at or after i that is not a JPEG fill byte (0xFF), or len(data).
    Stripped 64 kB at a time: the work grows with the run, not with the data after it."""
    while i < len(data):
        chunk = data[i:i + 65536]
        rest = len(chunk.lstrip(b"\xff"))
        if rest:
            return i + len(chunk) - rest
        i += len(chunk)
    return len(data)


def _jpeg_segments(data: bytes):
    """(marker, index, next index) of the JPEG's segments after its SOI, in order, up to MAX_JPEG_SEGMENTS of them;
    a run of fill bytes is one item (marker 0xFF), skipped at once. Ends early at a byte that is not a marker (junk)
    or at the end of the data. This runs on the event loop: a hostile header must not make it walk megabytes byte
    by byte."""
    if data[:2] != b"\xff\xd8":
        return
    i = 2
    for _ in range(MAX_JPEG_SEGMENTS):
        if i + 4 > len(data) or data[i] != 0xFF:
            return
        marker = data[i + 1]
        if marker == 0xFF:  # fill bytes: go to the last 0xFF of the run, before its marker
            end = _fill_end(data, i) - 1
        elif marker == 0x01 or 0xD0 <= marker <= 0xD8:  # markers without a length field
            end = i + 2
        else:
            end = i + 2 + int.from_bytes(data[i + 2:i + 4], "big")
        yield marker, i, end
        i = end


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a JPEG's frame header (SOFn segment), None when it has none among its first
    MAX_JPEG_SEGMENTS segments."""
    for marker, i, _ in _jpeg_segments(data):
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):  # SOFn: precision, height, width
            if i + 9 > len(data):
                return None
            return int.from_bytes(data[i + 7:i + 9], "big"), int.from_bytes(data[i + 5:i + 7], "big")
        if marker == 0xDA:
            return None
    return None


def _check_jpeg_cost(data: bytes) -> None:
    """Refuse a JPEG whose decode would cost more than its pixels do: more than MAX_JPEG_SCANS scans (counted as
    SOS markers anywhere in the data, an upper bound: inside the entropy-coded data a 0xFF byte is always followed
    by 0x00 or a marker), or a header that Pillow would walk one byte at a time in Python (junk, more than
    MAX_JPEG_FILL_BYTES fill bytes, or more than MAX_JPEG_SEGMENTS segments before the first scan)."""
    scans = data.count(b"\xff\xda")
    if scans > MAX_JPEG_SCANS:
        raise InvalidInput(f"JPEG has {scans} scans; at most {MAX_JPEG_SCANS} are accepted (each scan is one more "
                           f"pass of the decoder over the whole frame)")
    fill = 0
    for marker, i, end in _jpeg_segments(data):
        if marker == 0xDA:
            return
        if marker == 0xFF:
            fill += end - i
            if fill > MAX_JPEG_FILL_BYTES:
                break
    raise InvalidInput(f"JPEG header does not reach its first scan within {MAX_JPEG_SEGMENTS} segments and "
                       f"{MAX_JPEG_FILL_BYTES} fill bytes, without junk between them")


def _png_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG's IHDR chunk, None when the signature or IHDR is missing."""
    if data[:8] != b"\x89PNG\r\n\x1a\n" or data[12:16] != b"IHDR" or len(data) < 24:
        return None
    return int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")


_HEADER_READERS = {pb.Image.JPEG: _jpeg_size, pb.Image.PNG: _png_size}


def _check_declared(image: pb.Image, camera: PinholeCamera | None) -> None:
    if image.width == 0 or image.height == 0:
        raise InvalidInput(f"image width and height must be positive, got {image.width}x{image.height}")
    if camera is not None and (image.width, image.height) != (camera.width, camera.height):
        raise InvalidInput(f"image is {image.width}x{image.height} but the intrinsics are for "
                           f"{camera.width}x{camera.height}")
    if image.encoding not in (pb.Image.JPEG, pb.Image.PNG, pb.Image.RAW_RGB8, pb.Image.RAW_GRAY8):
        raise InvalidInput(f"image encoding must be JPEG, PNG, RAW_RGB8 or RAW_GRAY8, got {image.encoding}")


def _raw_channels(image: pb.Image, data: bytes) -> int:
    channels = 3 if image.encoding == pb.Image.RAW_RGB8 else 1
    expected = image.width * image.height * channels
    if len(data) != expected:
        raise InvalidInput(f"{pb.Image.Encoding.Name(image.encoding)} image of {image.width}x{image.height} needs "
                           f"{expected} bytes, got {len(data)}")
    return channels


def _check(image: pb.Image, data: bytes, camera: PinholeCamera | None) -> None:
    _check_declared(image, camera)
    if image.encoding in _FORMATS:
        size = _HEADER_READERS[image.encoding](data)
        if size is None:
            raise InvalidInput(f"image data is not a readable {_FORMATS[image.encoding]} file")
        if size != (image.width, image.height):
            raise InvalidInput(f"image declared {image.width}x{image.height} but is {size[0]}x{size[1]}")
    else:
        _raw_channels(image, data)


# `image.data` copies the bytes at every access: each function below reads it once.

def check_image(image: pb.Image, camera: PinholeCamera | None) -> None:
    """Validate an image from its header only, for estimators that never look at pixels.

    Reading the size from the JPEG/PNG header takes microseconds; a full decode of a 640x480 JPEG
    takes milliseconds, which would dominate the cost of a ground-truth oracle.
    """
    data = image.data
    if data:
        _check(image, data, camera)


def _decode_rgb(data: bytes, fmt: str) -> np.ndarray:
    """HxWx3 uint8 RGB from JPEG/PNG bytes, by Pillow: OpenCV's libjpeg and libpng print their warnings about
    corrupt data straight to stderr, which broke the server's JSON-lines log; Pillow reports them as exceptions
    and prints nothing. Its JPEG pixels equal OpenCV's (the same libjpeg-turbo decode); 16-bit PNGs are scaled
    to 8 bits as OpenCV does."""
    try:
        with Image.open(io.BytesIO(data), formats=[fmt]) as img:
            img.load()
            if img.mode.startswith("I"):  # 16-bit (or 32-bit) grey: the high byte, as OpenCV's IMREAD_COLOR
                grey = (np.asarray(img).astype(np.uint32) >> 8).clip(0, 255).astype(np.uint8)
                return np.repeat(grey[..., None], 3, axis=2)
            return np.array(img.convert("RGB"))
    except (OSError, SyntaxError, ValueError, UnidentifiedImageError, Image.DecompressionBombError):
        raise InvalidInput(f"image data could not be decoded as {fmt}") from None


def decode_image(image: pb.Image, camera: PinholeCamera | None) -> np.ndarray | None:
    """HxWx3 uint8 RGB (or HxW for RAW_GRAY8), None when the request has no image."""
    data = image.data
    if not data:
        return None
    _check(image, data, camera)
    if image.encoding in _FORMATS:
        if image.encoding == pb.Image.JPEG:
            _check_jpeg_cost(data)
        rgb = _decode_rgb(data, _FORMATS[image.encoding])
        if rgb.shape[:2] != (image.height, image.width):
            raise InvalidInput(f"image declared {image.width}x{image.height} but is {rgb.shape[1]}x{rgb.shape[0]}")
        return rgb
    channels = _raw_channels(image, data)
    shape = (image.height, image.width, 3) if channels == 3 else (image.height, image.width)
    return np.frombuffer(data, np.uint8).reshape(shape).copy()
