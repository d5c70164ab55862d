"""What a simulated device sends: pre-serialized EstimateRequests of the paper's size.

The paper's device sends about 100 kB per frame (a 90 kB JPEG plus 10 kB of tracker state). A
frame template holds everything but the per-request fields (session, frame id); protobuf lets two
serialized messages be concatenated and parsed as their merge, so each request is the template's
bytes plus a few bytes of header. The load generator then spends its CPU on sending, not on
re-serializing 100 kB per request, and the figures measure the server.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flextrack import wire
from flextrack.v1 import pose_estimation_pb2 as pb


@dataclass(frozen=True)
class FrameTemplate:
    capture_time_ns: int
    body: bytes  # a serialized EstimateRequest without session_id / frame_id


class Workload:
    """Frame templates a client cycles through, and the per-request header that completes them."""

    def __init__(self, templates: list[FrameTemplate]):
        if not templates:
            raise ValueError("a workload needs at least one frame")
        self.templates = templates

    def request(self, client: int, frame: int) -> bytes:
        template = self.templates[frame % len(self.templates)]
        header = pb.EstimateRequest(session_id=f"load-{client}", frame_id=frame).SerializeToString()
        return template.body + header

    @property
    def request_bytes(self) -> int:
        return len(self.templates[0].body)


def _pad(request: pb.EstimateRequest, payload_bytes: int, rng: np.random.Generator) -> None:
    """Fill client_state with random bytes so that the request is about `payload_bytes` long."""
    missing = payload_bytes - request.ByteSize()
    if missing > 0:
        request.client_state = rng.bytes(missing)


def _jpeg(rgb: np.ndarray, quality: int = 90) -> bytes:
    import cv2  # the load generator runs beside the server, so it has the server extra

    ok, data = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("cannot encode a frame as JPEG")
    return data.tobytes()


def synthetic(payload_kb: float, estimator: str = "", fps: float = 30.0, frames: int = 30,
              width: int = 640, height: int = 480, seed: int = 0) -> Workload:
    """Frames with a random 640x480 JPEG and capture times at `fps`: enough for an echo servicer."""
    rng = np.random.default_rng(seed)
    image = _jpeg(rng.integers(0, 256, (height // 8, width // 8, 3), dtype=np.uint8).repeat(8, 0).repeat(8, 1))
    templates = []
    for k in range(frames):
        req = pb.EstimateRequest(estimator=estimator, capture_time_ns=int(k * 1e9 / fps),
                                 image=pb.Image(encoding=pb.Image.JPEG, data=image, width=width, height=height))
        _pad(req, int(payload_kb * 1024), rng)
        templates.append(FrameTemplate(req.capture_time_ns, req.SerializeToString()))
    return Workload(templates)


def from_sequence(root: str | Path, payload_kb: float, estimator: str = "", max_frames: int = 60,
                  seed: int = 0) -> Workload:
    """Frames of a sequence folder: its capture times, intrinsics and (where it has them) rgb/ images."""
    from flextrack.formats import sequence as sequence_io

    seq = sequence_io.load(root)
    rng = np.random.default_rng(seed)
    intrinsics = wire.intrinsics_to_pb(seq.camera)
    step = max(1, len(seq.frame_ids) // max_frames)
    templates = []
    for frame_id, t_ns in list(zip(seq.frame_ids, seq.frame_times_ns))[::step][:max_frames]:
        req = pb.EstimateRequest(estimator=estimator, capture_time_ns=int(t_ns), object_id=seq.object_id,
                                 sequence=seq.name, intrinsics=intrinsics)
        rgb_path = seq.rgb_path(int(frame_id))
        if rgb_path.exists():
            import cv2

            bgr = cv2.imread(str(rgb_path), cv2.IMREAD_COLOR)
            req.image.CopyFrom(pb.Image(encoding=pb.Image.JPEG, data=_jpeg(bgr[:, :, ::-1]),
                                        width=bgr.shape[1], height=bgr.shape[0]))
        _pad(req, int(payload_kb * 1024), rng)
        templates.append(FrameTemplate(req.capture_time_ns, req.SerializeToString()))
    return Workload(templates)


def from_images(images: list[np.ndarray], camera, payload_kb: float, estimator: str = "", object_id: str = "",
                fps: float = 30.0, seed: int = 0) -> Workload:
    """Frames from RGB images (e.g. rendered views of an object) for an estimator that looks at pixels."""
    rng = np.random.default_rng(seed)
    intrinsics = wire.intrinsics_to_pb(camera)
    templates = []
    for k, rgb in enumerate(images):
        req = pb.EstimateRequest(estimator=estimator, object_id=object_id, capture_time_ns=int(k * 1e9 / fps),
                                 intrinsics=intrinsics,
                                 image=pb.Image(encoding=pb.Image.JPEG, data=_jpeg(rgb), width=rgb.shape[1],
                                                height=rgb.shape[0]))
        _pad(req, int(payload_kb * 1024), rng)
        templates.append(FrameTemplate(req.capture_time_ns, req.SerializeToString()))
    return Workload(templates)


def keypoint_frames(payload_kb: float, estimator: str = "pnp", fps: float = 30.0, frames: int = 30,
                    seed: int = 0) -> Workload:
    """Synthetic frames that a `pnp` estimator answers: the project's default object (the default server
    config's `objects.default`) turning slowly 0.6 m in front of a LineMOD camera, its registered 3D keypoints
    projected into each frame, and a random JPEG as the image. `flextrack loadtest` sends these by default, so
    that `flextrack serve` with its default config answers them OK."""
    from estimators.objects import load_object
    from flextrack.assets import default_object_model
    from flextrack.geometry import se3, so3
    from flextrack.geometry.camera import PinholeCamera

    keypoints_O = load_object("default", default_object_model()).keypoints
    camera = PinholeCamera.linemod()
    intrinsics = wire.intrinsics_to_pb(camera)
    rng = np.random.default_rng(seed)
    image = _jpeg(rng.integers(0, 256, (camera.height // 8, camera.width // 8, 3), dtype=np.uint8)
                  .repeat(8, 0).repeat(8, 1))
    templates = []
    for k in range(frames):
        T_CO = se3.make(so3.exp(np.array([0.3, 2 * np.pi * k / frames, 0.1])), np.array([0.0, 0.0, 0.6]))
        uv = camera.project(se3.transform_points(T_CO, keypoints_O))
        req = pb.EstimateRequest(estimator=estimator, object_id="default", capture_time_ns=int(k * 1e9 / fps),
                                 intrinsics=intrinsics,
                                 keypoints=[pb.Keypoint(id=i, u=float(u), v=float(v)) for i, (u, v) in enumerate(uv)],
                                 image=pb.Image(encoding=pb.Image.JPEG, data=image, width=camera.width,
                                                height=camera.height))
        _pad(req, int(payload_kb * 1024), rng)
        templates.append(FrameTemplate(req.capture_time_ns, req.SerializeToString()))
    return Workload(templates)
