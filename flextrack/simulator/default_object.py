"""The project's own default object, built by code: `python -m flextrack.simulator.default_object`.

An asymmetric composite (a box body, a cylinder arm, a cone, a tilted tab and a ball) so that no
rotation maps it onto itself, scaled to 150 mm across like the LineMOD cat, with a rich vertex-colour
pattern (a hue per part, a 3D checker, slanted stripes and dark spots) so that its pose is
unambiguous from texture as well as from shape and a network can learn it. Faces wholly inside
another part are dropped, so every vertex lies on the visible surface. Deterministic: the same
code writes the same bytes, PLY_SHA256, the ones the shipped network was trained on (a test
checks). `flextrack.assets` generates it on first use; no copy is tracked.

Written as a BOP model: `models/obj_000001.ply` (mm, flat per-face normals, RGBA per vertex) and
`models/models_info.json` (diameter, bounding box).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from matplotlib.colors import hsv_to_rgb
from scipy.spatial import ConvexHull
from scipy.spatial.distance import pdist

from flextrack import assets
from flextrack.formats import bop

OBJECT_ID = "default"
BOP_OBJ_ID = 1
DIAMETER_MM = 150.0
MAX_EDGE_MM = 5.0  # vertex spacing: dense enough that vertex colours read as texture
DEFAULT_DIR = assets.default_object_home()  # where `write` puts the models folder by default
# sha256 of the .ply `write` produces: the object the shipped PVNet model was trained on
PLY_SHA256 = "d3d419e53f6ae5fb135af60b06dc9c5021e7c4d87aa353bb6f71e662ad17c06f"
_EPS = 1e-3  # mm: a vertex on a part's boundary is not inside it


@dataclass(frozen=True)
class _Part:
    mesh: trimesh.Trimesh
    inside: Callable[[np.ndarray], np.ndarray]  # (N, 3) points -> (N,) strictly inside
    hue: float


def _local(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    return (points - T[:3, 3]) @ T[:3, :3]


def _pose(rz_deg: float, t, ry_deg: float = 0.0) -> np.ndarray:
    T = trimesh.transformations.rotation_matrix(np.radians(rz_deg), [0, 0, 1])
    T = T @ trimesh.transformations.rotation_matrix(np.radians(ry_deg), [0, 1, 0])
    T[:3, 3] = t
    return T


def _box(extents, T, hue) -> _Part:
    half = np.asarray(extents) / 2 - _EPS
    return _Part(trimesh.creation.box(extents, transform=T),
                 lambda p: np.all(np.abs(_local(p, T)) < half, axis=1), hue)


def _cylinder(radius, height, T, hue) -> _Part:
    def inside(p):
        q = _local(p, T)
        return (np.hypot(q[:, 0], q[:, 1]) < radius - _EPS) & (np.abs(q[:, 2]) < height / 2 - _EPS)
    return _Part(trimesh.creation.cylinder(radius, height, sections=40, transform=T), inside, hue)


def _cone(radius, height, T, hue) -> _Part:
    def inside(p):
        q = _local(p, T)
        return (q[:, 2] > _EPS) & (np.hypot(q[:, 0], q[:, 1]) < radius * (1 - q[:, 2] / height) - _EPS)
    return _Part(trimesh.creation.cone(radius, height, sections=40, transform=T), inside, hue)


def _ball(radius, centre, hue) -> _Part:
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=radius)
    mesh.apply_translation(centre)
    return _Part(mesh, lambda p: np.linalg.norm(p - centre, axis=1) < radius - _EPS, hue)


def _parts() -> list[_Part]:
    """The composite, in mm before scaling. No two parts share a plane (no coplanar faces)."""
    return [
        _box((96, 64, 44), _pose(0, (0, 0, 0)), hue=0.02),  # red body
        _cylinder(17, 58, _pose(0, (60, 14, 6), ry_deg=90), hue=0.58),  # blue arm along +x
        _cone(24, 60, _pose(0, (-22, -12, 14)), hue=0.14),  # yellow cone on top, off centre
        _box((36, 22, 18), _pose(25, (-55, 22, -10)), hue=0.33),  # green tab, turned 25 deg
        _ball(16, np.array([14.0, -36.0, -8.0]), hue=0.80),  # purple ball out of the -y side
    ]


def _flat_shaded(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices shared only by faces with the same normal, so edges stay sharp when rendered."""
    corners = vertices[faces]  # (M, 3, 3)
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    keys = np.concatenate([corners, np.repeat(normals[:, None], 3, axis=1)], axis=2).reshape(-1, 6)
    unique, inverse = np.unique(np.round(keys, 6), axis=0, return_inverse=True)
    return unique[:, :3], unique[:, 3:], inverse.reshape(-1, 3)


def _colours(points: np.ndarray, hue: np.ndarray) -> np.ndarray:
    """RGBA uint8: part hue, 3D checker (18 mm), slanted stripes and seeded dark spots."""
    checker = np.floor(points / 18.0).astype(int).sum(axis=1) % 2
    stripes = np.sin(2 * np.pi * (points @ np.array([0.7, 0.3, -0.5])) / 40.0)
    h = (hue + 0.06 * stripes) % 1.0
    s = 0.55 + 0.35 * checker
    v = 0.95 - 0.40 * checker * (stripes > 0)
    spots = np.random.default_rng(7).uniform(-75, 75, size=(60, 3))
    near = np.min(np.linalg.norm(points[:, None] - spots[None], axis=2), axis=1)
    v = np.where(near < 9.0, 0.15, v)
    rgb = hsv_to_rgb(np.stack([h, s, v], axis=1))
    return np.hstack([np.round(rgb * 255), np.full((len(points), 1), 255)]).astype(np.uint8)


def build() -> trimesh.Trimesh:
    """The default object as a mesh in mm, centred on its bounding box, 150 mm in diameter."""
    parts = _parts()
    all_v, all_f, all_hue, offset = [], [], [], 0
    for i, part in enumerate(parts):
        mesh = part.mesh.copy()
        mesh.unmerge_vertices()
        v, f = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, MAX_EDGE_MM)
        others = [p for j, p in enumerate(parts) if j != i]
        buried = np.zeros(len(v), dtype=bool)
        for other in others:
            buried |= other.inside(v)
        f = f[~np.all(buried[f], axis=1)]
        all_v.append(v)
        all_f.append(f + offset)
        all_hue.append(np.full(len(v), part.hue))
        offset += len(v)
    vertices, faces = np.vstack(all_v), np.vstack(all_f)
    hue_of = np.concatenate(all_hue)
    face_hue = hue_of[faces[:, 0]]

    hull = vertices[ConvexHull(vertices).vertices]
    scale = DIAMETER_MM / pdist(hull).max()
    vertices = vertices * scale
    vertices -= (vertices.min(axis=0) + vertices.max(axis=0)) / 2

    v, n, f = _flat_shaded(vertices, faces)
    vertex_hue = np.zeros(len(v))
    vertex_hue[f.ravel()] = np.repeat(face_hue, 3)
    return trimesh.Trimesh(v, f, vertex_normals=n, vertex_colors=_colours(v, vertex_hue), process=False)


def models_info(vertices_mm: np.ndarray) -> dict:
    """BOP models_info entry: diameter and axis-aligned bounding box, mm."""
    lo, hi = vertices_mm.min(axis=0), vertices_mm.max(axis=0)
    hull = vertices_mm[ConvexHull(vertices_mm).vertices]
    info = {"diameter": round(float(pdist(hull).max()), 4)}
    info.update({f"min_{a}": round(float(lo[i]), 4) for i, a in enumerate("xyz")})
    info.update({f"size_{a}": round(float(hi[i] - lo[i]), 4) for i, a in enumerate("xyz")})
    return info


def ply_bytes(mesh: trimesh.Trimesh) -> bytes:
    return trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=True)


def write(models_dir: str | Path = DEFAULT_DIR) -> Path:
    """Write obj_000001.ply and models_info.json into `models_dir`; returns the .ply path."""
    models_dir = Path(models_dir)
    models_dir.mkdir(parents=True, exist_ok=True)
    mesh = build()
    ply = models_dir / f"obj_{BOP_OBJ_ID:06d}.ply"
    ply.write_bytes(ply_bytes(mesh))
    bop.write_models_info(models_dir / "models_info.json", {BOP_OBJ_ID: models_info(np.asarray(mesh.vertices))})
    return ply


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_DIR, help="models folder to write")
    args = parser.parse_args(argv)
    ply = write(args.out)
    print(f"wrote {ply} ({ply.stat().st_size / 1024:.0f} kB) and {ply.parent / 'models_info.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
