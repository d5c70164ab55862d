"""`flextrack guide-view --object MESH.ply --out guide.png`: the outline a user lines the real object up
with before tracking starts (as Vuforia's Model Targets start), and the pose that outline stands for.

The object is drawn by the project's renderer (pyrender on EGL) at a working distance where its
diameter spans `--fill` of the image's shorter side, seen from `--elevation-deg` above its x-y plane
and `--azimuth-deg` around its +z axis, with +z up in the image, its box centre on the principal
point. The PNG is an overlay for the camera preview: transparent, the object faint, its outline
opaque. Beside it, `guide.json` holds the pose (T_CO, OpenCV camera axes, metres, and the wire's
Pose fields) and the intrinsics (the wire's Intrinsics fields): once the outline covers the object,
send that pose as the first prior, with a covariance as loose as the alignment (e.g. 30 mm / 15 deg).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from flextrack.geometry.camera import PinholeCamera, look_at

OUTLINE_RGBA = (0, 255, 0, 255)
FILL_ALPHA = 0.35


@dataclass(frozen=True)
class GuideOptions:
    camera: PinholeCamera
    fill: float = 0.5  # the share of the image's shorter side the object's diameter spans
    elevation_deg: float = 30.0
    azimuth_deg: float = 0.0
    distance_m: float | None = None  # None: from `fill`
    outline_px: int = 3


def guide_pose(vertices_m: np.ndarray, diameter_m: float, options: GuideOptions) -> np.ndarray:
    """T_CO of the guide view: the camera looks at the box centre from the options' direction and distance."""
    cam = options.camera
    distance = options.distance_m or min(cam.fx, cam.fy) * diameter_m / (options.fill * min(cam.width, cam.height))
    center = (vertices_m.min(axis=0) + vertices_m.max(axis=0)) / 2.0
    el, az = np.radians(options.elevation_deg), np.radians(options.azimuth_deg)
    eye = center + distance * np.array([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.sin(el)])
    R = look_at(eye, center, up=(0.0, 0.0, 1.0))  # the box centre on the optical axis
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ eye
    return T


def draw(model_path: Path, T_CO: np.ndarray, options: GuideOptions) -> np.ndarray:
    """(H, W, 4) uint8 RGBA: the rendered object at FILL_ALPHA, its outer outline opaque."""
    import cv2

    from flextrack.simulator.render import Renderer

    with Renderer(options.camera, model_path) as renderer:
        frame = renderer.render(T_CO)
    rgba = np.zeros((*frame.mask.shape, 4), np.uint8)
    rgba[..., :3] = frame.rgb
    rgba[..., 3] = np.where(frame.mask, round(255 * FILL_ALPHA), 0)
    contours, _ = cv2.findContours(frame.mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    cv2.drawContours(rgba, contours, -1, OUTLINE_RGBA, options.outline_px, lineType=cv2.LINE_AA)
    return rgba


def describe(model_path: Path, T_CO: np.ndarray, camera: PinholeCamera) -> dict:
    """The JSON beside the PNG: the pose in the wire's convention and the camera it was drawn for."""
    from flextrack import wire

    pose, intrinsics = wire.pose_to_pb(T_CO), wire.intrinsics_to_pb(camera)
    return {
        "object": str(model_path),
        "T_CO": np.round(T_CO, 9).tolist(),
        "pose": {f.name: getattr(pose, f.name) for f in pose.DESCRIPTOR.fields},
        "intrinsics": {f.name: (list(getattr(intrinsics, f.name)) if f.name == "distortion" else getattr(intrinsics, f.name))
                       for f in intrinsics.DESCRIPTOR.fields},
        "convention": "T_CO maps object points (m) into the camera frame (OpenCV: x right, y down, z forward); "
                      "pose holds the same as flextrack.v1.Pose (quaternion w first)",
    }


def _intrinsics(text: str) -> tuple[float, float, float, float]:
    try:
        values = tuple(float(v) for v in text.split(","))
    except ValueError:
        values = ()
    if len(values) != 4 or not all(np.isfinite(values)) or values[0] <= 0 or values[1] <= 0:
        raise argparse.ArgumentTypeError(f"expected FX,FY,CX,CY in pixels (fx, fy > 0), got {text!r}")
    return values  # type: ignore[return-value]


def _size(text: str) -> tuple[int, int]:
    w, sep, h = text.lower().partition("x")
    if not (sep and w.isdigit() and h.isdigit() and int(w) > 0 and int(h) > 0):
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels, e.g. 640x480, got {text!r}")
    return int(w), int(h)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.description = __doc__.split("\n\n")[1].replace("\n", " ")
    parser.add_argument("--object", type=Path, required=True, metavar="MESH.ply",
                        help="the object's mesh: a BOP .ply in mm (models_info.json beside it gives its diameter)")
    parser.add_argument("--out", type=Path, required=True, metavar="GUIDE.png",
                        help="the overlay PNG to write; the pose goes beside it, as GUIDE.json")
    parser.add_argument("--size", type=_size, default="640x480", metavar="WxH", help="image size in pixels")
    parser.add_argument("--intrinsics", type=_intrinsics, metavar="FX,FY,CX,CY",
                        help="the phone camera's intrinsics in pixels (default: LineMOD's focal lengths, 572.4 and 573.6 px at "
                             "640 wide, scaled to --size, the principal point at the image centre)")
    parser.add_argument("--fill", type=float, default=GuideOptions.fill,
                        help="share of the image's shorter side the object's diameter spans (sets the distance)")
    parser.add_argument("--distance-m", type=float, help="camera to object centre, metres (default: from --fill)")
    parser.add_argument("--elevation-deg", type=float, default=GuideOptions.elevation_deg,
                        help="camera height above the object's x-y plane, in degrees (BOP models: z is up)")
    parser.add_argument("--azimuth-deg", type=float, default=GuideOptions.azimuth_deg,
                        help="camera direction around the object's +z axis, in degrees (0: from -y)")


def problem(args: argparse.Namespace) -> str | None:
    if not args.object.is_file():
        return f"--object {args.object}: no such file"
    if args.out.suffix.lower() != ".png":
        return f"--out {args.out}: give a .png file (the pose is written beside it as .json)"
    if not 0 < args.fill <= 1:
        return f"--fill must be in (0, 1], got {args.fill:g}"
    if args.distance_m is not None and not args.distance_m > 0:
        return f"--distance-m must be > 0, got {args.distance_m:g}"
    if not abs(args.elevation_deg) < 89.0:
        return f"--elevation-deg must be within (-89, 89) (the image's up is the object's +z), got {args.elevation_deg:g}"
    return None


def camera_of(args: argparse.Namespace) -> PinholeCamera:
    width, height = args.size
    if args.intrinsics is not None:
        return PinholeCamera(*args.intrinsics, width, height)
    base = PinholeCamera.linemod()
    s = width / base.width
    return PinholeCamera(base.fx * s, base.fy * s, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


def run(args: argparse.Namespace) -> int:
    import cv2

    from estimators.objects import load_object

    why = problem(args)
    if why is None:
        try:
            model = load_object(args.object.stem, args.object)
        except ValueError as exc:
            why = str(exc)
    if why is not None:
        print(f"flextrack guide-view: {why}", file=sys.stderr)
        return 2
    options = GuideOptions(camera_of(args), args.fill, args.elevation_deg, args.azimuth_deg, args.distance_m)
    T_CO = guide_pose(model.vertices, model.diameter_m, options)
    try:
        rgba = draw(args.object, T_CO, options)
    except (ImportError, RuntimeError, ValueError) as exc:  # no EGL / no GL driver, or a mesh pyrender refuses
        print(f"flextrack guide-view: cannot render {args.object}: {type(exc).__name__}: {exc}".splitlines()[0],
              file=sys.stderr)
        return 1
    if not rgba[..., 3].any():
        print(f"flextrack guide-view: the object is not in view at this pose ({args.object})", file=sys.stderr)
        return 1
    args.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(args.out), cv2.cvtColor(rgba, cv2.COLOR_RGBA2BGRA))
    pose_file = args.out.with_suffix(".json")
    pose_file.write_text(json.dumps(describe(args.object, T_CO, options.camera), indent=1) + "\n")
    center = (model.vertices.min(axis=0) + model.vertices.max(axis=0)) / 2.0
    print(f"wrote {args.out} and {pose_file}: the object's centre {np.linalg.norm(T_CO[:3, :3] @ center + T_CO[:3, 3]):.3f} m "
          f"away, seen from elevation {args.elevation_deg:g} deg, azimuth {args.azimuth_deg:g} deg")
    return 0
