"""The sparse viewpoint model: for views on a geodesic sphere around the object, points on the
silhouette's outline with their outward normals (both in the object frame), built once from the
mesh and cached on disk.

Per view the camera looks at the object's box centre from `distance_m`; the silhouette is the union
of the mesh's projected triangles, drawn with OpenCV (only the faces along the outline: those
between a face turned to the camera and one turned away, and open edges; the outer contour of their
union is the silhouette's), oversampled so that the object spans `image_px` pixels. Each contour
point gets the depth of the nearest outline vertex and is lifted back to 3D; its 2D normal is
lifted to the 3D direction in the image plane. `fg_dist` / `bg_dist` are how far (m, at the point's
depth) a line along the normal stays inside / outside the silhouette, so that lines across thin
parts can be shortened (SRT3D's idea).
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import trimesh
from scipy.spatial import cKDTree

from flextrack.geometry.camera import look_at as camera_look_at

MODEL_FORMAT = 1


@dataclass(frozen=True)
class ViewpointModel:
    directions: np.ndarray  # (V, 3) unit vectors from the object's centre to the camera, object frame
    points: np.ndarray  # (V, N, 3) m, object frame
    normals: np.ndarray  # (V, N, 3) unit, object frame, outward and perpendicular to the view ray
    fg_dist: np.ndarray  # (V, N) m along the normal inwards until the silhouette is left
    bg_dist: np.ndarray  # (V, N) m along the normal outwards until the silhouette is met again
    center: np.ndarray  # (3,) the box centre the views look at
    # per view, the same numbers a row a coordinate, for `project_lines`' one matrix product a pose: the points
    # then the normals (V, 3, 2N), the distances fg, bg (V, 2, N); the four fields above are views of them (and
    # the directions, of a (3, V) array)
    stacked: np.ndarray = field(init=False, repr=False, compare=False)
    dists: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self):
        n = self.points.shape[1]
        stacked = np.concatenate([self.points, self.normals], axis=1).transpose(0, 2, 1).astype(float, order="C")
        dists = np.stack([self.fg_dist, self.bg_dist], axis=1).astype(float, order="C")
        views = {
            "directions": np.ascontiguousarray(np.asarray(self.directions, float).T).T,
            "stacked": stacked,
            "dists": dists,
            "points": stacked[:, :, :n].transpose(0, 2, 1),
            "normals": stacked[:, :, n:].transpose(0, 2, 1),
            "fg_dist": dists[:, 0],
            "bg_dist": dists[:, 1],
        }
        for name, value in views.items():
            object.__setattr__(self, name, value)

    def closest_view(self, R_CO: np.ndarray, t_CO: np.ndarray) -> int:
        """The view whose direction is nearest the camera's direction as seen from the object."""
        cam_O = -(t_CO @ R_CO) - self.center  # camera centre in the object frame (its length changes no argmax)
        return int((cam_O @ self.directions.T).argmax())  # (3, V) contiguous: the product runs along the views

    def save(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp.npz")
        np.savez_compressed(tmp, directions=self.directions, points=self.points.astype(np.float32),
                            normals=self.normals.astype(np.float32), fg_dist=self.fg_dist.astype(np.float32),
                            bg_dist=self.bg_dist.astype(np.float32), center=self.center)
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: Path) -> ViewpointModel:
        with np.load(path) as z:
            return cls(z["directions"], z["points"].astype(float), z["normals"].astype(float),
                       z["fg_dist"].astype(float), z["bg_dist"].astype(float), z["center"])


def geodesic_directions(subdivisions: int) -> np.ndarray:
    """Unit vectors at the vertices of a subdivided icosahedron (4 -> 2562 views, 3 -> 642)."""
    return np.asarray(trimesh.creation.icosphere(subdivisions=subdivisions).vertices, dtype=float)


def look_at(direction: np.ndarray, center: np.ndarray, distance: float) -> tuple[np.ndarray, np.ndarray]:
    """R_CO, t_CO of a camera at centre + distance * direction looking at the centre (OpenCV axes)."""
    eye = center + distance * direction
    helper = np.array([0.0, 0.0, 1.0]) if abs(direction[2]) < 0.9 * np.linalg.norm(direction) else np.array([1.0, 0.0, 0.0])
    R = camera_look_at(eye, center, up=-helper)  # rows: camera axes in the object frame
    return R, -R @ eye


class _Silhouette:
    """Draws a mesh's silhouette outline in one view."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        mesh = trimesh.Trimesh(vertices, faces)  # merged, so that faces meeting at an edge share it
        self.vertices, self.faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        self.adjacent = mesh.face_adjacency
        self.face_normals = np.cross(self.vertices[self.faces[:, 1]] - self.vertices[self.faces[:, 0]],
                                     self.vertices[self.faces[:, 2]] - self.vertices[self.faces[:, 0]])
        uses = np.bincount(mesh.edges_unique_inverse, minlength=len(mesh.edges_unique))
        self.open_faces = np.unique(np.nonzero(uses[mesh.faces_unique_edges] == 1)[0])

    def outline(self, R: np.ndarray, t: np.ndarray, f: float, size: int, n_points: int):
        """Contour points (N, 3) and normals (N, 3) in the object frame, fg/bg distances (N,) m."""
        cam = self.vertices @ R.T + t
        uv = cam[:, :2] / cam[:, 2:3] * f + size / 2.0
        facing = np.einsum("ij,ij->i", self.face_normals @ R.T, cam[self.faces[:, 0]]) < 0
        turn = facing[self.adjacent[:, 0]] != facing[self.adjacent[:, 1]]
        rim = np.unique(np.concatenate([self.adjacent[turn].ravel(), self.open_faces]))
        mask = np.zeros((size, size), np.uint8)
        tri = np.round((uv - 0.5) * 16).astype(np.int32)[self.faces[rim]]
        for triangle in tri:  # one by one: fillPoly over many polygons fills their overlaps even-odd
            cv2.fillConvexPoly(mask, triangle, 1, lineType=cv2.LINE_8, shift=4)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        contours = [c for c in contours if len(c) >= 12]
        if not contours:
            raise ValueError("the mesh's silhouette has no outline in a view")
        mask = cv2.drawContours(np.zeros_like(mask), contours, -1, 1, thickness=cv2.FILLED)  # the whole silhouette
        contours = [c[:, 0, :].astype(float) for c in contours]
        # points spread evenly over the whole outline (every outer contour, by length)
        pts, nrm = [], []
        for c in contours:
            tangent = np.roll(c, -2, axis=0) - np.roll(c, 2, axis=0)
            normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
            normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
            probe = np.round(c + 2.5 * normal).astype(int)
            inside = mask[np.clip(probe[:, 1], 0, size - 1), np.clip(probe[:, 0], 0, size - 1)] > 0
            normal[inside] *= -1
            pts.append(c)
            nrm.append(normal)
        c, normal = np.vstack(pts), np.vstack(nrm)
        pick = np.linspace(0, len(c), n_points, endpoint=False).astype(int)
        c, normal = c[pick] + 0.5, normal[pick]  # pixel centres (OpenCV's fill is inclusive)
        # distances along the normal inside / outside the silhouette (raster px), up to `reach`
        reach = size // 4
        steps = np.arange(1, reach + 1)
        lin = c[:, None, :] - steps[None, :, None] * normal[:, None, :]
        lout = c[:, None, :] + steps[None, :, None] * normal[:, None, :]

        def first(xy, want_inside):
            xi = np.clip(xy[..., 0].astype(int), 0, size - 1)
            yi = np.clip(xy[..., 1].astype(int), 0, size - 1)
            hit = (mask[yi, xi] > 0) != want_inside
            any_ = hit.any(axis=1)
            return np.where(any_, np.argmax(hit, axis=1) + 1, reach).astype(float)

        fg_px, bg_px = first(lin, True), first(lout, False)
        rim_vertices = np.unique(self.faces[rim])
        _, nearest = cKDTree(uv[rim_vertices]).query(c)
        z = cam[rim_vertices[nearest], 2]
        rays = np.column_stack([(c - size / 2.0) / f, np.ones(len(c))])
        points_O = (rays * z[:, None] - t) @ R
        normals_O = np.column_stack([normal, np.zeros(len(c))]) @ R
        return points_O, normals_O, fg_px * z / f, bg_px * z / f


def build_viewpoint_model(vertices_m: np.ndarray, faces: np.ndarray, *, subdivisions: int = 4,
                          n_points: int = 200, image_px: int = 400, distance_m: float = 0.8) -> ViewpointModel:
    """Contour points and normals for every view of the geodesic sphere (see the module docstring)."""
    vertices_m = np.asarray(vertices_m, dtype=float)
    center = (vertices_m.min(axis=0) + vertices_m.max(axis=0)) / 2.0
    radius = float(np.max(np.linalg.norm(vertices_m - center, axis=1)))
    distance = max(distance_m, 3.0 * radius)
    size = int(image_px * 1.3)
    f = image_px * distance / (2.0 * radius)
    sil = _Silhouette(vertices_m, np.asarray(faces, dtype=np.int64))
    directions = geodesic_directions(subdivisions)
    pts, nrm, fgd, bgd = [], [], [], []
    for d in directions:
        R, t = look_at(d, center, distance)
        p, n, fg, bg = sil.outline(R, t, f, size, n_points)
        pts.append(p)
        nrm.append(n)
        fgd.append(fg)
        bgd.append(bg)
    return ViewpointModel(directions, np.array(pts), np.array(nrm), np.array(fgd), np.array(bgd), center)


def default_cache_dir() -> Path:
    """$FLEXTRACK_CACHE/region, else the user's cache ($XDG_CACHE_HOME or ~/.cache)/flextrack/region: one place
    that `flextrack prepare` fills and every later `flextrack serve` of the same user reads."""
    base = os.environ.get("FLEXTRACK_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.expanduser("~/.cache"), "flextrack")
    return Path(base) / "region"


def _mesh_arrays(vertices_m: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.ascontiguousarray(vertices_m, dtype=np.float64), np.ascontiguousarray(faces, dtype=np.int64)


def cache_path(vertices_m: np.ndarray, faces: np.ndarray, cache_dir: Path | None = None, **options) -> Path:
    """Where the model of this mesh and these options is cached: keyed by the mesh's bytes and the options."""
    vertices_m, faces = _mesh_arrays(vertices_m, faces)
    key = hashlib.sha256()
    key.update(vertices_m.tobytes())
    key.update(faces.tobytes())
    key.update(repr((MODEL_FORMAT, sorted(options.items()))).encode())
    return (cache_dir or default_cache_dir()) / f"viewpoints_{key.hexdigest()[:20]}.npz"


def cached_viewpoint_model(vertices_m: np.ndarray, faces: np.ndarray, cache_dir: Path | None = None,
                           **options) -> ViewpointModel:
    """The model from `cache_dir` when one was built for this mesh and these options, else built and saved."""
    vertices_m, faces = _mesh_arrays(vertices_m, faces)
    path = cache_path(vertices_m, faces, cache_dir, **options)
    if path.is_file():
        try:
            return ViewpointModel.load(path)
        except (OSError, ValueError, KeyError):
            pass  # a damaged cache file is rebuilt
    model = build_viewpoint_model(vertices_m, faces, **options)
    try:
        model.save(path)
    except OSError:
        pass  # a read-only cache still serves, rebuilt per process
    return model


@dataclass(frozen=True)
class ViewpointJob:
    """One viewpoint model to have in the cache: a mesh, the cache folder (None: the default) and the options."""

    vertices_m: np.ndarray
    faces: np.ndarray
    cache_dir: Path | None
    options: dict

    @property
    def path(self) -> Path:
        return cache_path(self.vertices_m, self.faces, self.cache_dir, **self.options)


def _build_into_cache(job: ViewpointJob) -> None:
    cached_viewpoint_model(job.vertices_m, job.faces, job.cache_dir, **job.options)


def prepare_viewpoint_models(jobs: list[ViewpointJob], processes: int | None = None) -> list[bool]:
    """Build the jobs' models that the cache lacks into it, `processes` at a time (default: one per CPU), in
    fresh (spawned) processes: a server's gRPC threads make forking unsafe. Per job, whether it was built
    (False: it was cached already). A job whose cache cannot be written is left to its first use."""
    missing: dict[Path, ViewpointJob] = {}
    for job in jobs:
        if not job.path.is_file():
            missing.setdefault(job.path, job)  # one build per mesh and options, however many ask for it
    todo = list(missing.values())
    workers = max(1, min(len(todo), processes or os.cpu_count() or 1))
    if workers == 1:
        for job in todo:
            _build_into_cache(job)
    elif todo:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as pool:
            list(pool.map(_build_into_cache, todo))
    return [job.path in missing for job in jobs]
