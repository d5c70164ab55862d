"""Training samples for the PVNet-style network, rendered by the project.

Two stages, so that the slow part (rendering) runs once and training pays only for cheap 2D work:

1. `render_views` renders the object alone (the simulator's renderer in object-only mode) at random poses around the working
   distances, with random lighting, and keeps for each view a square crop at half the camera
   resolution (the resolution the network sees): RGB + coverage (alpha), and the 2D keypoints.
2. `PatchSampler` builds training patches from those crops at train time: random background
   (noise, gradients, shapes, crops of the simulator's procedural room textures), random scale/rotation/position (truncation included), occluders,
   colour jitter, blur, noise and JPEG artefacts; targets are the mask and, per output pixel,
   the unit vectors towards each keypoint.

Coordinates follow OpenCV (pixel centres at integers). The network input is the frame halved
with area averaging, and its output grid is halved again: output cell (i, j) is the full-frame
point (4 j + 1.5, 4 i + 1.5).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from flextrack.geometry import se3, so3
from flextrack.geometry.camera import PinholeCamera, look_at

INPUT_SCALE = 2  # frame -> network input


def full_to_input(uv: np.ndarray) -> np.ndarray:
    """Frame pixel coordinates -> network-input coordinates (area halving)."""
    return (np.asarray(uv, dtype=float) - 0.5) / INPUT_SCALE


def look_at_pose(rng: np.random.Generator, camera: PinholeCamera, target: np.ndarray,
                 dist_range: tuple[float, float] = (0.45, 1.5), elevation_deg: tuple[float, float] = (15.0, 75.0),
                 roll_deg: float = 15.0, margin_px: float = 60.0) -> np.ndarray:
    """T_WC of a camera above the z = 0 plane (z up) looking at `target` from a random azimuth,
    elevation and distance, turned so that the target lands anywhere in the image, with some roll."""
    d = rng.uniform(*dist_range)
    el, az = np.radians(rng.uniform(*elevation_deg)), rng.uniform(0, 2 * np.pi)
    position = target + d * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    R0 = look_at(position, target).T  # R_WC: the camera looks at the target, y down (world z is up) ...
    u = rng.uniform(margin_px, camera.width - margin_px)
    v = rng.uniform(margin_px, camera.height - margin_px)
    ray = np.array([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, 1.0])
    ray /= np.linalg.norm(ray)
    axis = np.cross([0.0, 0.0, 1.0], ray)  # ... then turns so that the target lands at pixel (u, v)
    angle = np.arccos(np.clip(ray[2], -1, 1))
    R_align = so3.exp(axis / (np.linalg.norm(axis) + 1e-12) * angle)
    roll = so3.exp(ray * np.radians(rng.uniform(-roll_deg, roll_deg)))
    return se3.make(R0 @ R_align.T @ roll.T, position)


def random_pose(rng: np.random.Generator, camera: PinholeCamera, centre_O: np.ndarray,
                dist_range: tuple[float, float], elevation_deg: tuple[float, float] = (-5.0, 88.0)) -> np.ndarray:
    """T_CO seen from the object's upper hemisphere (its z axis up, as it stands on a table; BOP
    models are so aligned), the object anywhere in view, with up to 25 degrees of camera roll."""
    T_OC = look_at_pose(rng, camera, centre_O, dist_range, elevation_deg, roll_deg=25.0, margin_px=40.0)
    return se3.inverse(T_OC)


@dataclass
class RenderedViews:
    """Object-only crops at network-input resolution."""

    rgba: np.ndarray  # (N, S, S, 4) uint8, alpha = coverage
    keypoints: np.ndarray  # (N, K, 2) float32, crop coordinates (network-input px)
    poses: np.ndarray  # (N, 4, 4) T_CO

    def save(self, path: str | Path) -> None:
        np.savez(path, rgba=self.rgba, keypoints=self.keypoints, poses=self.poses)

    @classmethod
    def load(cls, path: str | Path) -> RenderedViews:
        with np.load(path) as data:
            return cls(data["rgba"], data["keypoints"], data["poses"])


def crop_size_for(diameter_m: float, camera: PinholeCamera, min_dist_m: float) -> int:
    """Side of the square crop (input px) that holds the object at its closest distance."""
    extent = diameter_m * camera.fx / min_dist_m / INPUT_SCALE
    return int(np.ceil((extent + 16) / 16) * 16)


def random_light(rng: np.random.Generator) -> tuple[np.ndarray, float, float]:
    """A light direction from the camera's side, an intensity and an ambient level."""
    d = rng.normal(size=3)
    d[2] = abs(d[2]) + 0.3  # shine away from the camera, into the scene
    return d / np.linalg.norm(d), rng.uniform(1.0, 6.0), rng.uniform(0.1, 0.6)


def render_views(model_path: str | Path, keypoints_O: np.ndarray, diameter_m: float, n: int, seed: int,
                 camera: PinholeCamera | None = None, dist_range: tuple[float, float] = (0.45, 1.5),
                 progress=None) -> RenderedViews:
    """n object-only views at random poses, cropped around the object at network-input resolution."""
    camera = camera or PinholeCamera.linemod()
    rng = np.random.default_rng(seed)
    size = crop_size_for(diameter_m, camera, dist_range[0])
    from flextrack.simulator.render import Renderer

    renderer = Renderer(camera, model_path)
    vertices = np.asarray(renderer.mesh.vertices)
    centre_O = (vertices.min(axis=0) + vertices.max(axis=0)) / 2
    rgba_all = np.zeros((n, size, size, 4), np.uint8)
    kps_all = np.zeros((n, len(keypoints_O), 2), np.float32)
    poses = np.zeros((n, 4, 4))
    try:
        for i in range(n):
            T_CO = random_pose(rng, camera, centre_O, dist_range)
            light_dir, intensity, ambient = random_light(rng)
            frame = renderer.render(T_CO, light_dir_C=light_dir, light_intensity=intensity, ambient=ambient)
            rgba = np.dstack([frame.rgb, np.where(frame.mask, 255, 0).astype(np.uint8)])
            half = cv2.resize(rgba, (camera.width // INPUT_SCALE, camera.height // INPUT_SCALE),
                              interpolation=cv2.INTER_AREA)
            kp = full_to_input(camera.project(se3.transform_points(T_CO, keypoints_O)))
            x0, y0 = np.round(kp[-1] - size / 2).astype(int)  # last keypoint: the centre
            padded = np.zeros((size, size, 4), np.uint8)
            sx0, sy0 = max(x0, 0), max(y0, 0)
            sx1, sy1 = min(x0 + size, half.shape[1]), min(y0 + size, half.shape[0])
            if sx1 > sx0 and sy1 > sy0:
                padded[sy0 - y0:sy1 - y0, sx0 - x0:sx1 - x0] = half[sy0:sy1, sx0:sx1]
            rgba_all[i], kps_all[i], poses[i] = padded, kp - [x0, y0], T_CO
            if progress is not None:
                progress(1)
    finally:
        renderer.close()
    return RenderedViews(rgba_all, kps_all, poses)


# ---- train-time composition -------------------------------------------------------------------

def room_textures(seeds=range(1000, 1008)) -> list[np.ndarray]:
    """The simulator's procedural room textures (table, floor, walls, boxes) for seeds that no
    evaluation or experiment uses; backgrounds that look like the rooms the tracker sees."""
    from flextrack.simulator.scene import make_scene

    textures = {}
    for seed in seeds:
        for quad in make_scene(seed).quads:
            textures[id(quad.texture)] = quad.texture
    return list(textures.values())


def texture_crop(rng: np.random.Generator, texture: np.ndarray, h: int, w: int) -> np.ndarray:
    """A randomly scaled and rotated crop of a texture, tiled where it runs out."""
    scale = rng.uniform(0.1, 1.5)
    M = cv2.getRotationMatrix2D((w / 2, h / 2), rng.uniform(0, 360), scale)
    M[:, 2] += rng.uniform(0, texture.shape[1], size=2)
    return cv2.warpAffine(texture, M, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_WRAP).astype(np.float32)


def random_background(rng: np.random.Generator, h: int, w: int, textures=()) -> np.ndarray:
    """A cluttered RGB uint8 background: room texture, smooth noise or a gradient, plus random shapes."""
    if textures and rng.random() < 0.4:
        img = texture_crop(rng, textures[rng.integers(len(textures))], h, w) * rng.uniform(0.5, 1.3)
    elif rng.random() < 0.5:
        cells = rng.integers(2, 12)
        low = rng.uniform(0, 255, size=(cells, cells, 3)).astype(np.float32)
        img = cv2.resize(low, (w, h), interpolation=cv2.INTER_CUBIC)
    else:
        c0, c1 = rng.uniform(0, 255, size=(2, 3))
        a = rng.uniform(0, 2 * np.pi)
        ramp = (np.cos(a) * np.arange(w)[None, :] + np.sin(a) * np.arange(h)[:, None]) / max(h, w)
        ramp = (ramp - ramp.min()) / (np.ptp(ramp) + 1e-6)
        img = c0 + (c1 - c0) * ramp[..., None]
    img = np.clip(img, 0, 255).astype(np.uint8)
    for _ in range(rng.integers(0, 25 if rng.random() < 0.7 else 3)):
        draw_random_shape(rng, img, rng.uniform(0, 255, size=3))
    sigma = rng.uniform(0, 20)
    return np.clip(img + rng.normal(0, sigma, size=img.shape), 0, 255).astype(np.uint8)


def draw_random_shape(rng: np.random.Generator, img: np.ndarray, colour, centre=None, scale=None) -> None:
    """Draws a filled rectangle, ellipse, polygon or thick line in place (on a 3- or 1-channel image)."""
    h, w = img.shape[:2]
    cx, cy = centre if centre is not None else (rng.uniform(0, w), rng.uniform(0, h))
    r = scale if scale is not None else rng.uniform(3, max(h, w) / 3)
    colour = tuple(float(c) for c in np.atleast_1d(colour))
    kind = rng.integers(4)
    if kind == 0:
        cv2.rectangle(img, (int(cx - r), int(cy - r * rng.uniform(0.3, 1))), (int(cx + r), int(cy + r)), colour, -1)
    elif kind == 1:
        cv2.ellipse(img, (int(cx), int(cy)), (int(r), int(r * rng.uniform(0.3, 1))), rng.uniform(0, 180), 0, 360,
                    colour, -1)
    elif kind == 2:
        k = rng.integers(3, 7)
        ang = np.sort(rng.uniform(0, 2 * np.pi, size=k))
        rad = r * rng.uniform(0.4, 1.0, size=k)
        pts = np.stack([cx + rad * np.cos(ang), cy + rad * np.sin(ang)], axis=1).astype(np.int32)
        cv2.fillPoly(img, [pts], colour)
    else:
        a = rng.uniform(0, np.pi)
        p0 = (int(cx - r * np.cos(a)), int(cy - r * np.sin(a)))
        p1 = (int(cx + r * np.cos(a)), int(cy + r * np.sin(a)))
        cv2.line(img, p0, p1, colour, int(rng.integers(1, max(2, int(r / 3)))))


def jitter_colour(rng: np.random.Generator, rgb: np.ndarray) -> np.ndarray:
    """Per-channel gain, brightness, contrast and gamma; float32 in, float32 out (0..255)."""
    gain = rng.uniform(0.75, 1.25, size=3) * rng.uniform(0.6, 1.4)
    out = rgb * gain + rng.uniform(-25, 25)
    mean = out.mean()
    out = (out - mean) * rng.uniform(0.7, 1.3) + mean
    out = 255.0 * (np.clip(out, 0, 255) / 255.0) ** rng.uniform(0.7, 1.4)
    return out


class PatchSampler:
    """Random training patches (images, masks, keypoints) from object-only crops."""

    def __init__(self, views: RenderedViews, size: int = 128, seed: int = 0, textures=(),
                 normalised_share: float = 0.7, normalised_px: tuple[float, float] = (44.0, 84.0),
                 turn_deg: float = 45.0):
        self.views = views
        # In-plane turn of the object up to +-turn_deg: a hand-held camera rolls freely. The estimator
        # also runs its crop turned by 90, 180 and 270 deg, which brings any roll within 45 deg of one
        # of them, so +-45 covers every roll; +-180 (the network alone facing any roll) cost upright
        # accuracy at this network size (docs/pvnet.md).
        self.turn_deg = turn_deg
        self.textures = list(textures)
        # Most patches show the object at the size the estimator's crop pass gives it (its box side
        # about normalised_px); the rest at the size the distance gives (the whole-frame pass).
        self.normalised_share, self.normalised_px = normalised_share, normalised_px
        alpha = views.rgba[..., 3] > 0
        rows, cols = alpha.any(axis=2), alpha.any(axis=1)
        extent = lambda m: np.where(m.any(1), m.shape[1] - np.argmax(m[:, ::-1], 1) - np.argmax(m, 1), 1)
        self.box_side = np.maximum(extent(rows), extent(cols)).astype(float)
        self.size = size
        self.rng = np.random.default_rng(seed)

    def sample(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One patch: RGB uint8 (S, S, 3), mask uint8 (S, S), keypoints (K, 2) in patch coordinates."""
        rng, s = self.rng, self.size
        i = rng.integers(len(self.views.rgba))
        crop = self.views.rgba[i]
        kp = self.views.keypoints[i].astype(np.float64)
        # object: scale, in-plane rotation, and a position that may cut it at the patch border
        if rng.random() < self.normalised_share:
            scale = np.exp(rng.uniform(*np.log(self.normalised_px))) / self.box_side[i]
        else:
            scale = np.exp(rng.uniform(np.log(0.7), np.log(1.35)))
        angle = rng.uniform(-self.turn_deg, self.turn_deg)
        centre = rng.uniform(-0.1 * s, 1.1 * s, size=2) if rng.random() < 0.3 else rng.uniform(0.2 * s, 0.8 * s, 2)
        M = cv2.getRotationMatrix2D((float(kp[-1, 0]), float(kp[-1, 1])), angle, scale)
        M[:, 2] += centre - kp[-1]
        obj = cv2.warpAffine(crop, M, (s, s), flags=cv2.INTER_LINEAR, borderValue=0).astype(np.float32)
        kp = kp @ M[:, :2].T + M[:, 2]
        alpha = obj[..., 3:] / 255.0
        fg = jitter_colour(rng, obj[..., :3])
        img = alpha * fg + (1 - alpha) * random_background(rng, s, s, self.textures)
        mask = (alpha[..., 0] > 0.5).astype(np.uint8)
        if rng.random() < 0.4 and mask.any():  # an occluder over part of the object
            occ = np.zeros((s, s), np.uint8)
            ys, xs = np.nonzero(mask)
            j = rng.integers(len(xs))
            extent = np.sqrt(mask.sum())
            draw_random_shape(rng, occ, 1, centre=(xs[j], ys[j]), scale=rng.uniform(0.15, 0.5) * extent)
            occ_img = random_background(rng, s, s, self.textures).astype(np.float32)
            img = np.where(occ[..., None] > 0, occ_img, img)
            mask = mask & (occ == 0)
        img = jitter_colour(rng, img) if rng.random() < 0.5 else img
        if rng.random() < 0.3:
            img = cv2.GaussianBlur(img, (0, 0), rng.uniform(0.4, 1.3))
        img = np.clip(img + rng.normal(0, rng.uniform(0, 6), size=img.shape), 0, 255).astype(np.uint8)
        if rng.random() < 0.3:
            _, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, int(rng.integers(40, 95))])
            img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
        return img, mask, kp.astype(np.float32)

    def batch(self, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        imgs, masks, kps = zip(*(self.sample() for _ in range(n)))
        return np.stack(imgs), np.stack(masks), np.stack(kps)


def targets(masks: np.ndarray, kps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Output-grid targets: mask (B, h, w) float32 and unit vectors (B, 2K, h, w) to the keypoints.

    `masks` (B, S, S) are at input resolution; output cell (i, j) is input point (2 j + 0.5, 2 i + 0.5).
    """
    b, s, _ = masks.shape
    h = s // 2
    m = masks.reshape(b, h, 2, h, 2).mean(axis=(2, 4)) > 0.5
    grid = np.arange(h) * 2 + 0.5
    dx = kps[:, :, 0, None, None] - grid[None, None, None, :]  # (B, K, 1, w)
    dy = kps[:, :, 1, None, None] - grid[None, None, :, None]  # (B, K, h, 1)
    dx, dy = np.broadcast_arrays(dx, dy)
    norm = np.sqrt(dx * dx + dy * dy) + 1e-6
    vec = np.stack([dx / norm, dy / norm], axis=2).reshape(b, -1, h, h)
    return m.astype(np.float32), vec.astype(np.float32)
