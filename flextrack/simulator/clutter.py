"""Frames of an object in clutter, after LineMOD-Occluded's real scenes, written as a BOP folder.

Each frame: the object rendered (object-only mode of the simulator's renderer, random light) at a
random pose (camera on the upper hemisphere, 0.6-1.2 m, any roll, the object anywhere in view) over
a crowded background (a table texture under dozens of textured, striped and plain shapes, some in
the object's own colours), with occluders drawn over it (up to `max_occlusion` of its pixels), then
a camera's imperfections: white balance and exposure, blur, sensor noise and JPEG. Ground truth and
intrinsics go to scene_gt.json / scene_camera.json, the visible share to scene_gt_info.json, and the
object's model to models/, so that `flextrack evaluate prior --bop OUT --obj-id 1` scores any
estimator on them as on the real LineMOD frames.

    python -m flextrack.simulator.clutter --out out/clutter --frames 40 --seed 0
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from flextrack.formats import bop
from flextrack.geometry import se3, so3
from flextrack.geometry.camera import PinholeCamera
from flextrack.simulator.scene import tile_texture, wall_texture, wood_texture


@dataclass(frozen=True)
class ClutterStyle:
    shapes: tuple[int, int] = (25, 60)  # background pieces
    occluders: tuple[int, int] = (0, 3)  # pieces over the object
    max_occlusion: float = 0.5  # share of the object's pixels the occluders may hide
    object_colour_share: float = 0.25  # background pieces in the object's own colours (distractors)
    distance_m: tuple[float, float] = (0.6, 1.2)
    noise_sigma: float = 3.0  # grey levels
    blur_px: tuple[float, float] = (0.0, 0.9)  # Gaussian sigma
    jpeg_quality: tuple[int, int] = (75, 95)


def _texture(rng: np.random.Generator, size: int) -> np.ndarray:
    kind = rng.integers(4)
    if kind == 0:
        return wood_texture(rng, size)
    if kind == 1:
        return tile_texture(rng, size)
    if kind == 2:
        return wall_texture(rng, size)
    period = rng.uniform(4, 24)  # stripes or checks, a printed box
    y, x = np.mgrid[0:size, 0:size]
    a, b = rng.uniform(0, 255, 3), rng.uniform(0, 255, 3)
    pattern = (np.sin(x / period) > 0) ^ ((np.sin(y / period) > 0) & bool(rng.integers(2)))
    return np.where(pattern[..., None], a, b).astype(np.uint8)


def _shape_mask(rng: np.random.Generator, h: int, w: int, centre: np.ndarray, size: float) -> np.ndarray:
    mask = np.zeros((h, w), np.uint8)
    kind = rng.integers(3)
    if kind == 0:  # a box's face or a book
        half = rng.uniform(0.3, 1.0, 2) * size
        box = cv2.boxPoints(((float(centre[0]), float(centre[1])), (float(2 * half[0]), float(2 * half[1])),
                             float(rng.uniform(0, 180))))
        cv2.fillConvexPoly(mask, np.round(box).astype(np.int32), 1)
    elif kind == 1:  # a bowl, a can seen from above
        axes = (int(rng.uniform(0.3, 1.0) * size), int(rng.uniform(0.3, 1.0) * size))
        cv2.ellipse(mask, (int(centre[0]), int(centre[1])), axes, float(rng.uniform(0, 180)), 0, 360, 1, -1)
    else:  # anything else
        n = rng.integers(3, 8)
        angles = np.sort(rng.uniform(0, 2 * np.pi, n))
        radii = rng.uniform(0.4, 1.0, n) * size
        pts = centre + np.column_stack([np.cos(angles), np.sin(angles)]) * radii[:, None]
        cv2.fillPoly(mask, [np.round(pts).astype(np.int32)], 1)
    return mask.astype(bool)


def _paint(rng: np.random.Generator, image: np.ndarray, mask: np.ndarray, palette: np.ndarray | None) -> None:
    """Fill `mask` with a texture, or a shaded plain colour (from `palette` when given)."""
    h, w = image.shape[:2]
    if palette is not None or rng.random() < 0.4:
        colour = palette[rng.integers(len(palette))] if palette is not None else rng.uniform(0, 255, 3)
        yy, xx = np.mgrid[0:h, 0:w]
        shade = 0.75 + 0.5 * ((xx * rng.normal() + yy * rng.normal()) / max(h, w) % 1.0)[..., None]
        fill = np.clip(colour * shade, 0, 255)
    else:
        tex = _texture(rng, 256)
        fill = cv2.resize(tex, (w, h), interpolation=cv2.INTER_LINEAR) if rng.random() < 0.5 else \
            np.tile(tex, (h // 256 + 1, w // 256 + 1, 1))[:h, :w]
    image[mask] = fill[mask]


def background(rng: np.random.Generator, h: int, w: int, style: ClutterStyle, palette: np.ndarray) -> np.ndarray:
    table = cv2.resize(_texture(rng, 512), (w, h), interpolation=cv2.INTER_LINEAR)
    image = table.astype(np.float64)
    for _ in range(rng.integers(*style.shapes)):
        mask = _shape_mask(rng, h, w, rng.uniform([0, 0], [w, h]), rng.uniform(15, 120))
        _paint(rng, image, mask, palette if rng.random() < style.object_colour_share else None)
    return image


def random_pose(rng: np.random.Generator, camera: PinholeCamera, center: np.ndarray, style: ClutterStyle) -> np.ndarray:
    """Camera on the upper hemisphere (z up, as BOP models stand), any roll, the object anywhere in view."""
    azimuth, elevation = rng.uniform(0, 2 * np.pi), np.radians(rng.uniform(10, 80))
    direction = np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    z = -direction
    x = np.cross(np.array([0.0, 0.0, 1.0]), z)
    x /= np.linalg.norm(x)
    R = so3.exp(np.array([0.0, 0.0, rng.uniform(-np.pi, np.pi)])) @ np.stack([x, np.cross(z, x), z])
    distance = rng.uniform(*style.distance_m)
    t = -R @ (center + distance * direction)
    # moved in the image plane: the centre anywhere in the middle 70 % of the frame
    u, v = rng.uniform(0.15, 0.85) * camera.width, rng.uniform(0.15, 0.85) * camera.height
    t[:2] += np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy]) * t[2]
    return se3.make(R, t)


def cluttered_frame(rng: np.random.Generator, renderer, T_CO: np.ndarray, style: ClutterStyle):
    """(rgb uint8, visible share of the object) for one pose."""
    light = rng.normal(size=3) + np.array([0.0, 0.0, 1.5])
    frame = renderer.render(T_CO, light_dir_C=light / np.linalg.norm(light), light_intensity=rng.uniform(1.5, 5.0),
                            ambient=rng.uniform(0.15, 0.5))
    h, w = frame.mask.shape
    palette = frame.rgb[frame.mask][:: max(1, int(frame.mask.sum()) // 50)].astype(np.float64) \
        if frame.mask.any() else rng.uniform(0, 255, (5, 3))
    image = background(rng, h, w, style, palette)
    image[frame.mask] = frame.rgb[frame.mask]
    visible = frame.mask.copy()
    ys, xs = np.nonzero(frame.mask)
    if len(xs):
        for _ in range(rng.integers(*style.occluders)):
            size = rng.uniform(0.25, 0.7) * max(np.ptp(xs), np.ptp(ys), 10)
            centre = np.array([xs.mean(), ys.mean()]) + rng.normal(0, 0.6, 2) * np.array([np.ptp(xs), np.ptp(ys)])
            mask = _shape_mask(rng, h, w, centre, size)
            if (visible & ~mask).sum() < (1 - style.max_occlusion) * frame.mask.sum():
                continue  # it would hide too much
            _paint(rng, image, mask, None)
            visible &= ~mask
    # the camera: white balance and exposure, blur, noise, JPEG
    image = image * rng.uniform(0.85, 1.15, 3) * rng.uniform(0.8, 1.2)
    sigma = rng.uniform(*style.blur_px)
    if sigma > 0.3:
        image = cv2.GaussianBlur(image, (0, 0), sigma)
    image = np.clip(image + rng.normal(0, style.noise_sigma, image.shape), 0, 255).astype(np.uint8)
    _, jpeg = cv2.imencode(".jpg", cv2.cvtColor(image, cv2.COLOR_RGB2BGR),
                            [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(*style.jpeg_quality))])
    rgb = cv2.cvtColor(cv2.imdecode(jpeg, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    share = float(visible.sum() / max(frame.mask.sum(), 1))
    return rgb, share


def write_bop_folder(out: Path, frames: int, seed: int, model_path: Path | None = None,
                     style: ClutterStyle = ClutterStyle(), camera: PinholeCamera | None = None) -> Path:
    """`frames` cluttered frames of the object (default: the project's) as out/test/000001/, object id 1."""
    from flextrack import assets
    from flextrack.simulator.render import Renderer, load_model

    camera = camera or PinholeCamera.linemod()
    model_path = Path(model_path) if model_path else assets.default_object_model()
    (out / "models").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(model_path, out / "models" / "obj_000001.ply")
    info_path = model_path.parent / "models_info.json"
    if info_path.is_file():
        info = bop.read_models_info(info_path)
        bop.write_models_info(out / "models" / "models_info.json", {1: next(iter(info.values()))})
    (out / "camera.json").write_text(json.dumps({"fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
                                                 "width": camera.width, "height": camera.height}))
    scene = out / "test" / "000001"
    (scene / "rgb").mkdir(parents=True, exist_ok=True)
    vertices = np.asarray(load_model(model_path).vertices)
    center = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    rng = np.random.default_rng(seed)
    poses, Ks, infos = {}, {}, {}
    with Renderer(camera, model_path) as renderer:
        for i in range(frames):
            T = random_pose(rng, camera, center, style)
            rgb, share = cluttered_frame(rng, renderer, T, style)
            cv2.imwrite(str(scene / "rgb" / f"{i:06d}.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
            poses[i], Ks[i], infos[str(i)] = T, camera.K, [{"visib_fract": share}]
    bop.write_scene_gt(scene / "scene_gt.json", poses, obj_id=1)
    bop.write_scene_camera(scene / "scene_camera.json", Ks)
    (scene / "scene_gt_info.json").write_text(json.dumps(infos, indent=1))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m flextrack.simulator.clutter", description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--frames", type=int, default=40)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--model", type=Path, default=None, help="BOP .ply (mm); default: the project's object")
    args = parser.parse_args(argv)
    write_bop_folder(args.out, args.frames, args.seed, args.model)
    print(f"wrote {args.frames} cluttered frames to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
