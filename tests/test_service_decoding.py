"""Request decoding: images in every encoding, sizes, intrinsics and keypoint checks."""

import math

import cv2
import numpy as np
import pytest

from estimators.base import InvalidInput
from flextrack.v1 import pose_estimation_pb2 as pb
from service.request_decoding import check_image, decode_camera, decode_image, decode_keypoints

_yy, _xx = np.mgrid[0:48, 0:64]
RGB = np.stack([_xx * 4, _yy * 5, (_xx + _yy) * 2], axis=2).astype(np.uint8)  # smooth: JPEG keeps it close


def encoded(ext: str, image=RGB) -> bytes:
    return cv2.imencode(ext, cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image)[1].tobytes()


def intrinsics(**kw) -> pb.Intrinsics:
    return pb.Intrinsics(**{"fx": 500.0, "fy": 500.0, "cx": 32.0, "cy": 24.0, "width": 64, "height": 48, **kw})


@pytest.mark.parametrize("encoding, data, exact", [
    (pb.Image.PNG, encoded(".png"), True),
    (pb.Image.JPEG, encoded(".jpg"), False),
    (pb.Image.RAW_RGB8, RGB.tobytes(), True),
])
def test_images_decode_to_rgb_and_pass_the_header_check(encoding, data, exact):
    image = pb.Image(encoding=encoding, data=data, width=64, height=48)
    camera = decode_camera(intrinsics())
    check_image(image, camera)
    rgb = decode_image(image, camera)
    assert rgb.shape == (48, 64, 3) and rgb.dtype == np.uint8
    assert np.array_equal(rgb, RGB) if exact else np.abs(rgb.astype(int) - RGB).mean() < 4


def test_gray_raw_image_decodes_to_hxw():
    gray = RGB[:, :, 0].copy()
    image = pb.Image(encoding=pb.Image.RAW_GRAY8, data=gray.tobytes(), width=64, height=48)
    assert np.array_equal(decode_image(image, None), gray)


@pytest.mark.parametrize("image, message", [
    (pb.Image(encoding=pb.Image.JPEG, data=b"not a jpeg at all", width=64, height=48), "JPEG"),
    (pb.Image(encoding=pb.Image.PNG, data=encoded(".jpg"), width=64, height=48), "PNG"),
    (pb.Image(encoding=pb.Image.PNG, data=encoded(".png"), width=640, height=480), "64x48"),
    (pb.Image(encoding=pb.Image.JPEG, data=encoded(".jpg"), width=32, height=48), "64x48"),
    (pb.Image(encoding=pb.Image.RAW_RGB8, data=RGB.tobytes()[:-1], width=64, height=48), "9216 bytes"),
    (pb.Image(encoding=pb.Image.ENCODING_UNSPECIFIED, data=b"xx", width=64, height=48), "encoding"),
    (pb.Image(encoding=pb.Image.PNG, data=encoded(".png"), width=0, height=48), "positive"),
])
def test_bad_images_are_invalid_input_in_both_paths(image, message):
    for check in (check_image, decode_image):
        with pytest.raises(InvalidInput, match=message):
            check(image, None)


def test_image_size_must_match_the_intrinsics():
    image = pb.Image(encoding=pb.Image.PNG, data=encoded(".png"), width=64, height=48)
    with pytest.raises(InvalidInput, match="intrinsics are for 640x480"):
        check_image(image, decode_camera(intrinsics(width=640, height=480)))


def test_intrinsics():
    assert decode_camera(pb.Intrinsics()) is None
    camera = decode_camera(intrinsics(distortion=[0.1, -0.2, 0.0, 0.0, 0.01]))
    assert camera.fx == 500.0 and camera.distortion == (0.1, -0.2, 0.0, 0.0, 0.01)
    for bad, message in [(intrinsics(fx=0.0), "fx and fy must be"), (intrinsics(fy=-3.0), "fx and fy must be"),
                         (intrinsics(fy=1e-12), "fx and fy must be"), (intrinsics(fx=1e7), "fx and fy must be"),
                         (intrinsics(cx=math.nan), "finite"), (intrinsics(fx=math.inf), "finite"),
                         (intrinsics(cx=1e6), "principal point"),
                         (intrinsics(width=0), "width and height"), (intrinsics(distortion=[0.1, 0.2]), "coefficients"),
                         (intrinsics(distortion=[-1e300, 0, 0, 0]), "within"),
                         (intrinsics(distortion=[0.1, math.nan, 0, 0]), "finite")]:
        with pytest.raises(InvalidInput, match=message):
            decode_camera(bad)


def test_keypoints():
    kp = decode_keypoints([pb.Keypoint(id=3, u=1.5, v=2.5), pb.Keypoint(id=0, u=4.0, v=5.0)])
    assert np.array_equal(kp, [[3, 1.5, 2.5], [0, 4.0, 5.0]])
    assert decode_keypoints([]).shape == (0, 3)
    with pytest.raises(InvalidInput, match="finite"):
        decode_keypoints([pb.Keypoint(id=0, u=math.nan, v=1.0)])


def test_a_hostile_jpeg_header_is_refused_without_walking_it_byte_by_byte():
    """Megabytes of fill bytes, or of empty segments, before any frame header: refused as soon as the scan
    gives up (a bounded number of segments, fill runs skipped at once), not after a per-byte walk."""
    for data in (b"\xff\xd8" + b"\xff" * 7_000_000, b"\xff\xd8" + b"\xff\xe0\x00\x02" * 1_000_000):
        image = pb.Image(encoding=pb.Image.JPEG, data=data, width=640, height=480)
        with pytest.raises(InvalidInput):
            check_image(image, decode_camera(intrinsics(width=640, height=480)))
    padded = encoded(".jpg")[:2] + b"\xff" * 1000 + encoded(".jpg")[2:]  # fill bytes are legal JPEG
    check_image(pb.Image(encoding=pb.Image.JPEG, data=padded, width=64, height=48),
                decode_camera(intrinsics(width=64, height=48)))
