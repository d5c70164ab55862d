"""The room around the object: a textured table in a textured room, lit differently per seed.

World W: z up, the table top is the plane z = 0 centred on the origin (the object stands on it),
the floor is at z = -TABLE_HEIGHT_M. Textures are procedural (seeded numpy), so that a sequence's
frames have features everywhere and two seeds give two looks. The description is plain data; the
renderer turns it into pyrender nodes.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

TABLE_HEIGHT_M = 0.75
TABLE_SIZE_M = (1.6, 1.0)
ROOM_HALF_M = 3.5
CEILING_M = 2.6  # above the table top


@dataclass(frozen=True)
class TexturedQuad:
    """A rectangle (4 corners, counter-clockwise seen from the side it faces) with a tiled texture."""

    corners: np.ndarray  # (4, 3) world, m
    texture: np.ndarray  # (H, W, 3) uint8
    repeats: tuple[float, float]  # texture tiles along the first and second edge


@dataclass(frozen=True)
class Lighting:
    ambient: float  # ambient intensity (grey)
    sun_direction_W: np.ndarray  # direction the directional light travels, unit
    sun_intensity: float  # lux
    lamp_position_W: np.ndarray  # point light above the table
    lamp_intensity: float  # candela
    lamp_colour: np.ndarray  # rgb in [0, 1]


@dataclass(frozen=True)
class SceneStyle:
    quads: tuple[TexturedQuad, ...]
    lighting: Lighting
    seed: int


def _smooth_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Band-limited noise in [0, 1]: random grid upsampled with bicubic interpolation."""
    grid = rng.random((cells, cells)).astype(np.float32)
    img = cv2.resize(grid, (size, size), interpolation=cv2.INTER_CUBIC)
    return np.clip(img, 0.0, 1.0)


def _colourise(value: np.ndarray, dark, light) -> np.ndarray:
    dark, light = np.asarray(dark, float), np.asarray(light, float)
    return np.clip(dark + value[..., None] * (light - dark), 0, 255).astype(np.uint8)


def wood_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size] / size
    warp = _smooth_noise(rng, size, 6)
    grain = 0.5 + 0.5 * np.sin(2 * np.pi * (14 * x + 3 * warp + 0.3 * np.sin(2 * np.pi * 2 * y)))
    fine = _smooth_noise(rng, size, 64)
    base = rng.uniform([70, 40, 15], [140, 90, 50])
    return _colourise(0.6 * grain + 0.4 * fine, base * 0.55, base * 1.35)


def tile_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    y, x = np.mgrid[0:size, 0:size] / size
    tiles = (np.floor(x * 4) + np.floor(y * 4)) % 2
    grout = (np.minimum((x * 4) % 1, (y * 4) % 1) < 0.04).astype(float)
    value = 0.35 + 0.45 * tiles + 0.2 * _smooth_noise(rng, size, 32) - 0.5 * grout
    tint = rng.uniform([120, 110, 100], [220, 210, 200])
    return _colourise(np.clip(value, 0, 1), tint * 0.3, tint)


def wall_texture(rng: np.random.Generator, size: int = 512) -> np.ndarray:
    """Plaster with a few coloured posters: corners and edges for any camera to see."""
    value = 0.7 + 0.3 * _smooth_noise(rng, size, 24)
    tint = rng.uniform([150, 150, 140], [240, 235, 225])
    img = _colourise(value, tint * 0.6, tint)
    for _ in range(int(rng.integers(3, 7))):
        w, h = rng.integers(size // 10, size // 3, size=2)
        x0, y0 = rng.integers(0, size - w), rng.integers(0, size - h)
        colour = rng.integers(0, 255, size=3)
        stripes = (np.arange(w)[None, :, None] // max(2, w // 6)) % 2
        img[y0:y0 + h, x0:x0 + w] = np.where(stripes, colour, 255 - colour).astype(np.uint8)
    return img


def _box_quads(lo, hi, texture, tile_m: float) -> list[TexturedQuad]:
    """The 6 outward-facing faces of an axis-aligned box."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    faces = [
        [(x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)],  # top
        [(x0, y1, z0), (x1, y1, z0), (x1, y0, z0), (x0, y0, z0)],  # bottom
        [(x0, y0, z0), (x1, y0, z0), (x1, y0, z1), (x0, y0, z1)],  # -y
        [(x1, y1, z0), (x0, y1, z0), (x0, y1, z1), (x1, y1, z1)],  # +y
        [(x0, y1, z0), (x0, y0, z0), (x0, y0, z1), (x0, y1, z1)],  # -x
        [(x1, y0, z0), (x1, y1, z0), (x1, y1, z1), (x1, y0, z1)],  # +x
    ]
    quads = []
    for f in faces:
        c = np.asarray(f, dtype=float)
        a, b = np.linalg.norm(c[1] - c[0]), np.linalg.norm(c[3] - c[0])
        quads.append(TexturedQuad(c, texture, (max(a / tile_m, 1e-3), max(b / tile_m, 1e-3))))
    return quads


def _room_quads(floor, wall) -> list[TexturedQuad]:
    """Floor, ceiling and four walls facing inwards."""
    r, zf, zc = ROOM_HALF_M, -TABLE_HEIGHT_M, CEILING_M
    span = 2 * r / 1.5
    quads = [
        TexturedQuad(np.array([(-r, -r, zf), (r, -r, zf), (r, r, zf), (-r, r, zf)]), floor, (2 * r, 2 * r)),
        TexturedQuad(np.array([(-r, r, zc), (r, r, zc), (r, -r, zc), (-r, -r, zc)]), wall, (span, span)),
    ]
    for k in range(4):
        c, s = np.cos(k * np.pi / 2), np.sin(k * np.pi / 2)
        a = np.array([r * c - r * s, r * s + r * c])  # corner at (r, r) turned by k*90 deg
        b = np.array([r * c + r * s, r * s - r * c])  # corner at (r, -r) turned
        quads.append(TexturedQuad(np.array([(*a, zf), (*b, zf), (*b, zc), (*a, zc)]), wall,
                                  (span, (zc - zf) / 1.5)))
    return quads


def make_scene(seed: int) -> SceneStyle:
    """The room for sequence seed `seed`: textures, clutter and lighting all drawn from it."""
    rng = np.random.default_rng([seed, 0x5CE4E])
    wood, floor, wall = wood_texture(rng), tile_texture(rng), wall_texture(rng)
    tx, ty = TABLE_SIZE_M[0] / 2, TABLE_SIZE_M[1] / 2
    quads = _box_quads((-tx, -ty, -0.04), (tx, ty, 0.0), wood, 0.8)
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (tx - 0.08), sy * (ty - 0.08)
            quads += _box_quads((x - 0.03, y - 0.03, -TABLE_HEIGHT_M), (x + 0.03, y + 0.03, -0.04), wood, 0.5)
    quads += _room_quads(floor, wall)
    for _ in range(6):  # boxes on the floor along the walls: parallax and corners
        size = rng.uniform(0.2, 0.6, size=3)
        angle = rng.uniform(0, 2 * np.pi)
        dist = rng.uniform(1.8, ROOM_HALF_M - 0.4)
        cx, cy = dist * np.cos(angle), dist * np.sin(angle)
        lo = (cx - size[0] / 2, cy - size[1] / 2, -TABLE_HEIGHT_M)
        hi = (cx + size[0] / 2, cy + size[1] / 2, -TABLE_HEIGHT_M + size[2])
        quads += _box_quads(lo, hi, wall_texture(rng, 128), 0.3)

    elevation = rng.uniform(np.radians(35), np.radians(75))
    azimuth = rng.uniform(0, 2 * np.pi)
    sun = -np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    lighting = Lighting(
        ambient=float(rng.uniform(0.15, 0.45)),
        sun_direction_W=sun,
        sun_intensity=float(rng.uniform(1.5, 4.0)),
        lamp_position_W=np.array([*rng.uniform(-0.8, 0.8, size=2), rng.uniform(1.2, 2.2)]),
        lamp_intensity=float(rng.uniform(4.0, 15.0)),
        lamp_colour=rng.uniform(0.8, 1.0, size=3),
    )
    return SceneStyle(tuple(quads), lighting, seed)
