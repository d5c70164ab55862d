"""Pose refinement on the image's edges: the model's outline, drawn at the current pose, is pulled
onto the strongest nearby colour edge along its normals.

Why: a pose from PnP on voted keypoints is right to a pixel or two in 2D but a few per cent off in
depth (2 px of keypoint noise over an 80 px object), which is most of the ADD error. The object's
outline in the image is sharp to a fraction of a pixel, and its size fixes the depth. Each round
draws the silhouette (the mesh's triangles, four times oversampled), takes points along its
contour with their outward normals, finds the edge along each normal (the largest change of colour
within `search_px`, favouring the nearest), and solves the 6 pose parameters by robust least
squares (Cauchy loss, `_robust_gauss_newton`) on the points' distances to their edges along the
normals, with the starting pose's projected keypoints as a weak prior so that a few false edges
cannot drag it far. In the
last round, once the pose is near, the points left more than `fit_px` off their edge are dropped
and the pose solved again: the false edges are mostly the object's own print just inside its
outline, so they lean one way, and even down-weighted they pulled the pose too far (docs/pvnet.md).
`refine` also returns the last fit's Jacobian and residuals ("gn"), which the pvnet estimator turns
into the pose's covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import trimesh
from scipy.linalg import lapack

OVERSAMPLE = 4  # silhouette raster per image pixel
_FLANN_TREE = {"algorithm": 4, "leaf_max_size": 128}  # FLANN's single k-d tree (KDTREE_SINGLE): exact search


@dataclass(frozen=True)
class ContourRefineConfig:
    rounds: int = 3
    points: int = 160  # contour points per round
    search_px: float = 3.0  # how far along the normal an edge is looked for
    nearness_px: float = 2.0  # edges further than this count for less (Gaussian weight)
    min_edge: float = 6.0  # colour change (0-255 per px) below which a point finds no edge
    robust_px: float = 0.3  # scale of the Cauchy loss: an edge further off is most likely another edge
    step_px: int = 1  # width each side of the step an edge is measured as (no blur: it moved edges inwards)
    prior_weight: float = 0.02  # per keypoint, against the starting pose's projection: weak, the outline decides
    min_points: int = 30  # fewer points with an edge: the pose is kept as it is
    max_shift_px: float = 8.0  # a refined pose whose keypoints moved further is rejected
    fit_px: float = 1.0  # a contour point this near its edge after the fit counts as fitting
    trim: bool = True  # the last round solved again without the points over fit_px off their edge


def _dot2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products of (N, 2) arrays, as np.sum(a * b, axis=1) gives them, at a tenth of its cost."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1]


def _sample(image: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """The image (uint8) as float32, bilinear at the float32 points xy (..., 2), its border replicated: what
    cv2.remap of the whole image converted to float gives, converting only the part under the points (on
    whole frames the conversion cost more than the rest of the edge search). The part's integer corner is
    subtracted exactly and it holds every pixel the interpolation reads (remap rounds to 1/32 px)."""
    h, w = image.shape[:2]
    x0, y0 = (min(max(int(np.floor(xy[..., i].min())) - 1, 0), n - 1) for i, n in ((0, w), (1, h)))
    x1, y1 = (max(min(int(np.floor(xy[..., i].max())) + 3, n), x + 1) for i, n, x in ((0, w, x0), (1, h, y0)))
    return cv2.remap(image[y0:y1, x0:x1].astype(np.float32), xy[..., 0] - np.float32(x0), xy[..., 1] - np.float32(y0),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _nearest(points: np.ndarray, queries: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Index of the nearest of the points (N, 2) to each query (M, 2), as scipy's cKDTree finds it, at two thirds
    of its cost: cKDTree's build takes numpy's min and max over the columns, which this numpy does at ~13 ns an
    element (0.45 of its 0.6 ms on 8.6k points). FLANN's tree works in float32 (here about `origin`, near the
    points), whose rounding swapped 1 in 10^4 near-ties; its two nearest re-ranked in float64 swapped none of 83k."""
    tree = cv2.flann_Index((points - origin).astype(np.float32), _FLANN_TREE)
    two = tree.knnSearch((queries - origin).astype(np.float32), 2, params={})[0]
    a, b = points[two[:, 0]] - queries, points[two[:, 1]] - queries
    return np.where(_dot2(b, b) < _dot2(a, a), two[:, 1], two[:, 0])


def _project(K: np.ndarray, R: np.ndarray, t: np.ndarray, points_O: np.ndarray) -> np.ndarray:
    p = points_O @ R.T + t
    return (p[:, :2] / p[:, 2:3]) * np.array([K[0, 0], K[1, 1]]) + K[:2, 2]


class _Rows:
    """The fit's rows, set up once a fit so that each evaluation is a dozen numpy calls: the first
    len(normals) points' distances to their targets along their normals, then x and y of each remaining
    point (the keypoints) against its prior projection, weighted by w. Each row is a direction a (the
    normal, or w along x or y) times a point's projection, less a target: r = a . (u, v) - a . target."""

    def __init__(self, K, points, normals, targets, w, prior):
        m, k = len(normals), len(points) - len(normals)
        idx = np.concatenate([np.arange(m), np.repeat(np.arange(m, m + k), 2)])  # the point of each row
        a = np.zeros((m + 2 * k, 2))
        a[:m], a[m::2, 0], a[m + 1::2, 1] = normals, w, w
        goal = np.concatenate([targets, np.repeat(prior, 2, axis=0)])
        self.points = points[idx]
        # (u, v) = (fx, fy) * (x, y) / z + (cx, cy): a . (u, v) = a_u fx x / z + a_v fy y / z + a . (cx, cy)
        self.afx, self.afy = np.ascontiguousarray(a[:, 0] * K[0, 0]), np.ascontiguousarray(a[:, 1] * K[1, 1])
        self.b = _dot2(a, goal - K[:2, 2])

    def __call__(self, R, t) -> tuple[np.ndarray, np.ndarray]:
        """Residuals and their Jacobian w.r.t. [a rotation on the left of R, a shift of t] in the camera frame."""
        q = self.points @ R.T  # the points turned; camera frame P = q + t
        P = q + t
        iz = 1.0 / P[:, 2]
        nx, ny = P[:, 0] * iz, P[:, 1] * iz
        # per row, its gradient g w.r.t. P: a . d(u, v) / dP = (a_u fx / z, a_v fy / z, -(a_u fx x + a_v fy y) / z^2);
        # dP / d(rotation on the left) = -[q]x, so a row is [q x g, g]
        J = np.empty((len(q), 6))
        g0, g1 = J[:, 3], J[:, 4]
        np.multiply(self.afx, iz, out=g0)
        np.multiply(self.afy, iz, out=g1)
        g2 = J[:, 5]
        np.negative(g0 * nx + g1 * ny, out=g2)
        r = self.afx * nx + self.afy * ny - self.b
        np.subtract(q[:, 1] * g2, q[:, 2] * g1, out=J[:, 0])
        np.subtract(q[:, 2] * g0, q[:, 0] * g2, out=J[:, 1])
        np.subtract(q[:, 0] * g1, q[:, 1] * g0, out=J[:, 2])
        return r, J


def _robust_gauss_newton(rows: _Rows, R, t, scale: float, iterations: int = 100) -> tuple[np.ndarray, ...]:
    """The pose minimising sum_i rho(r_i^2), rho(z) = ln(1 + z / scale^2) (the Cauchy loss) over the
    rows' residuals: Levenberg-Marquardt on the residuals and Jacobian scaled for the loss as scipy's
    least_squares scales them (Triggs' correction), relinearised at each accepted pose, stopped where
    the cost falls by less than 1e-8 of itself (scipy's ftol). It solves scipy's least_squares(loss="cauchy",
    f_scale=scale) problem at a small part of the cost: scipy's general trust-region solver (an SVD
    per step, a dozen Python calls per evaluation) took more than half of the refinement's time.
    Returns the pose and the rows' residuals and Jacobian there."""
    r, J = rows(R, t)
    zz = (r / scale) ** 2
    c, lam = float(np.log1p(zz).sum()), 1.0  # damped at first (the step about the gradient's), as scipy's first
    # trust region: a full Gauss-Newton step from a start some px off jumped into another minimum of the robust cost
    for _ in range(iterations):
        rho1 = 1.0 / (1.0 + zz)
        js = np.sqrt(np.maximum(rho1 - 2.0 * zz * (rho1 * rho1), 1e-12))  # rho' + 2 rho'' r^2, floored
        Js = J * js[:, None]
        A, g = Js.T @ Js, Js.T @ (r * rho1 / js)
        damping = A.ravel()[::7] + 1e-12  # the diagonal (a view's stride, not fancy indexing: numpy calls are the cost)
        while True:
            D = A.copy()
            D.ravel()[::7] += lam * damping
            dx = -lapack.dgesv(D, g)[2]  # np.linalg.solve's LU, the same answer, without its checks' overhead
            R2, t2 = cv2.Rodrigues(dx[:3])[0] @ R, t + dx[3:]
            r2, J2 = rows(R2, t2)
            zz2 = (r2 / scale) ** 2
            c2 = float(np.log1p(zz2).sum())
            if c2 <= c or lam > 1e8:
                break
            lam *= 10.0
        if c2 > c:
            break
        converged = c - c2 <= 1e-8 * c or abs(dx).max() < 1e-10
        R, t, r, J, zz, c, lam = R2, t2, r2, J2, zz2, c2, max(lam / 10.0, 1e-9)
        if converged:
            break
    return R, t, r, J


class ContourRefiner:
    """Refines T_CO of one object against an image; holds the object's mesh and keypoints."""

    def __init__(self, vertices_m: np.ndarray, faces: np.ndarray, keypoints_m: np.ndarray,
                 config: ContourRefineConfig = ContourRefineConfig()):
        # vertices merged, so that faces meeting at an edge share its vertices
        mesh = trimesh.Trimesh(np.asarray(vertices_m, dtype=float), np.asarray(faces, dtype=np.int64))
        if len(mesh.faces) == 0:
            raise ValueError("contour refinement needs the object's mesh faces")
        self.vertices, self.faces = np.asarray(mesh.vertices), np.asarray(mesh.faces)
        self.vertices_T = np.ascontiguousarray(self.vertices.T)
        self.keypoints = np.asarray(keypoints_m, dtype=float)
        self.config = config
        self.prior_w = np.sqrt(config.prior_weight) * np.ones(len(self.keypoints))  # each keypoint prior row's weight
        # the edge search's samples along each normal (px), the boundaries between the w = 2 step_px samples inside
        # and outside that it measures the colour change at, and their weights (nearer edges favoured, none beyond
        # search_px)
        self.steps = np.arange(-config.search_px - config.step_px, config.search_px + config.step_px + 0.01, 0.5)
        self.boundaries = self.steps[2 * config.step_px:len(self.steps) - 2 * config.step_px + 1] - 0.25
        self.nearness = np.where(np.abs(self.boundaries) > config.search_px, 0.0,
                                 np.exp(-0.5 * (self.boundaries / config.nearness_px) ** 2))
        # The outline of a projected mesh is made of edges between a face turned towards the camera
        # and one turned away, and of open edges; only the faces along those need drawing (holes
        # inside do not change the outer contour), a few thousand of the object's faces at most.
        self.adjacent = [np.ascontiguousarray(side) for side in mesh.face_adjacency.T]  # the two faces of each edge
        self.face_normals = np.cross(self.vertices[self.faces[:, 1]] - self.vertices[self.faces[:, 0]],
                                     self.vertices[self.faces[:, 2]] - self.vertices[self.faces[:, 0]])
        # a face turns towards a camera at c = -R^T t (object frame) where n . (v0 - c) < 0, n . R^T t < -n . v0:
        # -n . v0 once here
        self.face_offsets = -np.einsum("ij,ij->i", self.face_normals, self.vertices[self.faces[:, 0]])
        uses = np.bincount(mesh.edges_unique_inverse, minlength=len(mesh.edges_unique))
        self.open_faces = np.zeros(len(self.faces), bool)  # the faces along open edges: always drawn
        self.open_faces[uses[mesh.faces_unique_edges].min(axis=1) == 1] = True

    def outline(self, K: np.ndarray, R: np.ndarray, t: np.ndarray, shape: tuple[int, int]):
        """The object's outline at pose (R, t): contour points (M, 2) in image px, their outward unit normals and
        their 3D points (object frame); None when it is out of view or too small."""
        x, y, z = R @ self.vertices_T + t[:, None]  # camera frame, one contiguous row per axis
        if z.min() <= 1e-3:
            return None
        u, v = K[0, 0] * x / z + K[0, 2], K[1, 1] * y / z + K[1, 2]
        lo = np.floor([u.min(), v.min()]) - 2
        hi = np.ceil([u.max(), v.max()]) + 2
        if np.any(hi < 0) or lo[0] > shape[1] or lo[1] > shape[0] or np.any(hi - lo > 2000):
            return None  # out of view, or so near that it fills far more than the frame
        uv = np.column_stack([u, v])
        size = ((hi - lo) * OVERSAMPLE).astype(int)
        mask = np.zeros((size[1], size[0]), np.uint8)
        facing = self.face_normals @ (R.T @ t) < self.face_offsets
        turn = facing[self.adjacent[0]] != facing[self.adjacent[1]]
        drawn = self.open_faces.copy()  # the faces along turning edges and the open ones, in order
        drawn[self.adjacent[0][turn]] = True
        drawn[self.adjacent[1][turn]] = True
        rim = np.flatnonzero(drawn)
        # coordinates in 1/16 raster px (shift=4), ((u - lo) OVERSAMPLE - 0.5) 16; raster px centre (i + 0.5) /
        # OVERSAMPLE image px
        tri = np.rint((uv[self.faces[rim]] - lo) * (16 * OVERSAMPLE) - 8).astype(np.int32)
        fill = cv2.fillConvexPoly  # (mask, points, colour, cv2.LINE_8, shift 4), positional: a third faster a call
        for triangle in tri:  # one by one: fillPoly on many polygons fills their overlaps even-odd
            fill(mask, triangle, 1, 8, 4)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        if not contours:
            return None
        c = max(contours, key=len)[:, 0, :].astype(float)
        if len(c) < 24:
            return None
        # `points` of the outline's pixels, evenly spaced, with the tangent over +-3 raster px and the outward
        # normal. The points are the outline pixels' centres: OpenCV's fill is inclusive, and the true outline
        # lies about there, not half a raster px further out. Outward is told by the contour's turning sense (its
        # signed area), not by probing the mask: only the faces along the outline are drawn, so the mask is a
        # band, and a probe inwards could land in its empty middle.
        pick = np.linspace(0, len(c), self.config.points, endpoint=False).astype(int)
        tangent = c[(pick + 3) % len(c)] - c[pick - 3]
        area2 = float(np.sum(c[:, 0] * np.roll(c[:, 1], -1) - np.roll(c[:, 0], -1) * c[:, 1]))
        turn = 1.0 if area2 > 0 else -1.0
        normal = np.stack([turn * tangent[:, 1], -turn * tangent[:, 0]], axis=1)
        normal /= np.maximum(np.sqrt(_dot2(normal, normal)), 1e-9)[:, None]
        c = c[pick]
        pts = (c + 0.5) / OVERSAMPLE + lo
        # 3D point under each contour point: its ray at the depth of the nearest projected vertex
        z = z[_nearest(uv, pts, lo)]
        rays = np.column_stack([(pts - K[:2, 2]) / np.array([K[0, 0], K[1, 1]]), np.ones(len(pts))])
        points_O = (rays * z[:, None] - t) @ R
        return pts, normal, points_O

    def _edges(self, image: np.ndarray, pts: np.ndarray, normals: np.ndarray):
        """Signed offsets along the normals to the chosen edge, and which points found one."""
        cfg, s = self.config, self.boundaries
        profile = _sample(image, (pts[:, None, :] + self.steps[None, :, None] * normals[:, None, :]).astype(np.float32))
        # a step between the means of the w px inside and the w px outside of each position: texture on
        # one side (the object's print) adds noise to it but does not move its peak, as a derivative's
        w = 2 * cfg.step_px
        csum = np.zeros((len(pts), profile.shape[1] + 1, profile.shape[2]), np.float32)
        np.cumsum(profile, axis=1, out=csum[:, 1:])
        inner = (csum[:, w:-w] - csum[:, :-2 * w]) / w
        outer = (csum[:, 2 * w:] - csum[:, w:-w]) / w
        d = outer - inner
        change = np.sqrt(d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1] + d[..., 2] * d[..., 2]) / cfg.step_px
        # the colour change per px, at the boundary between
        best = np.argmax(change * self.nearness, axis=1)
        rows = np.arange(len(pts))
        found = change[rows, best] >= cfg.min_edge
        # sub-step peak of the colour change (parabola through the best and its neighbours)
        b = np.minimum(np.maximum(best, 1), len(s) - 2)
        y0, y1, y2 = change[rows, b - 1], change[rows, b], change[rows, b + 1]
        denom = y0 - 2 * y1 + y2
        curved = np.abs(denom) > 1e-9
        frac = np.where(curved, 0.5 * (y0 - y2) / np.where(curved, denom, 1.0), 0.0)
        offset = s[b] + 0.5 * np.minimum(np.maximum(frac, -1.0), 1.0)
        return offset, found

    def _fit(self, K: np.ndarray, R: np.ndarray, t: np.ndarray, points_O: np.ndarray, normals: np.ndarray,
             targets: np.ndarray, prior: np.ndarray, trim: bool) -> tuple[np.ndarray, np.ndarray, dict]:
        """The pose (R, t) moved so that the contour points land on their edges along their normals,
        the keypoints held near their prior projections. Residual rows: one per contour point, then
        x and y per keypoint. `trim`: solved again without the points left over `fit_px` off."""
        rows = _Rows(K, np.vstack([points_O, self.keypoints]), normals, targets, self.prior_w, prior)
        R1, t1, r, J = _robust_gauss_newton(rows, R, t, self.config.robust_px)
        if trim:  # the one-sided false edges out, the same start solved again
            along = _dot2(_project(K, R1, t1, points_O) - targets, normals)
            near = np.abs(along) < self.config.fit_px
            if near.sum() >= self.config.min_points:
                return self._fit(K, R, t, points_O[near], normals[near], targets[near], prior, trim=False)
        # what the pose covariance is made of: the Jacobian at the solution (w.r.t. a left perturbation of
        # it in the camera frame, the wire convention) and the residuals, contour rows first
        return R1, t1, {"J": J, "r": r, "m": len(points_O)}

    def refine(self, image: np.ndarray, K: np.ndarray, T_CO: np.ndarray) -> tuple[np.ndarray, dict]:
        """The refined pose and what happened ({"points": edges used, "shift_px": keypoint motion,
        "kept": True when the starting pose was kept})."""
        cfg = self.config
        R, t = T_CO[:3, :3].copy(), T_CO[:3, 3].copy()
        prior = _project(K, R, t, self.keypoints)
        used, fit, gn = 0, 0.0, None
        for round_ in range(cfg.rounds):
            contour = self.outline(K, R, t, image.shape[:2])
            if contour is None:
                break
            pts, normals, points_O = contour
            offset, found = self._edges(image, pts, normals)
            used = int(found.sum())
            if used < cfg.min_points:
                break
            targets = pts[found] + offset[found, None] * normals[found]
            R, t, gn = self._fit(K, R, t, points_O[found], normals[found], targets, prior,
                                 trim=cfg.trim and round_ == cfg.rounds - 1)
            along = _dot2(_project(K, R, t, points_O[found]) - targets, normals[found])
            # share of the outline in view that lies on an edge (out of view, no edge can be checked)
            in_view = (pts[:, 0] >= 1) & (pts[:, 1] >= 1) & (pts[:, 0] <= image.shape[1] - 2) & (pts[:, 1] <= image.shape[0] - 2)
            fit = min(1.0, float(np.sum(np.abs(along) < cfg.fit_px)) / max(int(in_view.sum()), 1))
        shift = float(np.mean(np.linalg.norm(_project(K, R, t, self.keypoints) - prior, axis=1)))
        kept = used < cfg.min_points or shift > cfg.max_shift_px
        T = T_CO.copy()
        if not kept:
            T[:3, :3], T[:3, 3] = R, t
        return T, {"points": used, "shift_px": shift, "kept": kept, "fit": 0.0 if kept else fit, "gn": gn}
