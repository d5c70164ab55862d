"""The region estimator's inner loops against their plain formulas: the lines' projection, pixel sampling, contour
likelihood, Jacobians and histogram cells are written for speed (a row a coordinate, one matrix product a call,
numpy's own summation order where a decision hangs on it); these pin them to the straightforward maths they
replaced, so that a faster rewrite cannot move an answer unnoticed."""

import numpy as np
import pytest

from estimators.region import correspondence as corr
from estimators.region.correspondence import CellImage, LineModel, Lines, contour_distributions, project_lines
from estimators.region.histograms import ColourHistograms
from estimators.region.optimizer import line_jacobians, pose_error
from estimators.region.viewpoint_model import ViewpointModel, geodesic_directions
from flextrack.geometry import so3

K = np.array([[572.4, 0.0, 325.3], [0.0, 573.6, 242.0], [0.0, 0.0, 1.0]])
SHAPE = (480, 640)


@pytest.fixture(scope="module")
def model():
    """A synthetic viewpoint model: 42 views, 60 points each on a 4 cm sphere's rim-ish, random distances."""
    rng = np.random.default_rng(0)
    directions = geodesic_directions(1)
    points = rng.normal(0, 0.04, (len(directions), 60, 3))
    normals = rng.normal(0, 1, points.shape)
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    fg, bg = rng.uniform(0.005, 0.05, (2, len(directions), 60))
    return ViewpointModel(directions, points, normals, fg, bg, np.array([0.001, -0.002, 0.003]))


def plain_projection(model, R, t, margin_px=2.0):
    """The projection as first written: per point, the nearest view's contour point and normal in the image."""
    cam_O = -R.T @ t - model.center
    view = int(np.argmax(model.directions @ (cam_O / np.linalg.norm(cam_O))))
    P = model.points[view] @ R.T + t
    z = P[:, 2]
    uv = np.column_stack([K[0, 0] * P[:, 0] / z + K[0, 2], K[1, 1] * P[:, 1] / z + K[1, 2]])
    n_C = model.normals[view] @ R.T
    n2 = np.column_stack([K[0, 0] * (n_C[:, 0] * z - P[:, 0] * n_C[:, 2]) / z**2,
                          K[1, 1] * (n_C[:, 1] * z - P[:, 1] * n_C[:, 2]) / z**2])
    norm = np.linalg.norm(n2, axis=1)
    h, w = SHAPE
    keep = (norm > 1e-9) & (uv[:, 0] >= margin_px) & (uv[:, 0] <= w - 1 - margin_px) & \
        (uv[:, 1] >= margin_px) & (uv[:, 1] <= h - 1 - margin_px)
    scale_px = np.sqrt(K[0, 0] * K[1, 1]) / z[keep]
    return view, Lines(uv[keep], n2[keep] / norm[keep, None], P[keep], model.fg_dist[view][keep] * scale_px,
                       model.bg_dist[view][keep] * scale_px)


def pose(rng, depth=0.35):
    return so3.exp(rng.normal(0, 1.0, 3)), np.array([rng.normal(0, 0.05), rng.normal(0, 0.05), depth])


def test_the_projection_is_the_plain_formulas_and_a_repeat_is_served_again(model):
    rng = np.random.default_rng(1)
    for _ in range(20):
        R, t = pose(rng)
        view, want = plain_projection(model, R, t)
        assert model.closest_view(R, t) == view
        got = project_lines(model, R, t, K, SHAPE)
        for field in ("centers", "normals", "points_C", "fg_px", "bg_px"):
            np.testing.assert_allclose(getattr(got, field), getattr(want, field), rtol=1e-12, atol=1e-12)
        # the thread's last projections are given again (read-only: the callers share them); another pose is not
        assert project_lines(model, R.copy(), t.copy(), K, SHAPE) is got and not got.centers.flags.writeable
        assert project_lines(model, R, t + [1e-6, 0, 0], K, SHAPE) is not got
    R, t = pose(rng, depth=-0.3)  # behind the camera
    assert project_lines(model, R, t, K, SHAPE) is None


def test_the_viewpoint_models_fields_are_views_of_its_stacked_rows(model):
    n = model.points.shape[1]
    assert model.stacked.shape == (len(model.directions), 3, 2 * n)
    np.testing.assert_array_equal(model.stacked[7, :, :n].T, model.points[7])
    np.testing.assert_array_equal(model.stacked[7, :, n:].T, model.normals[7])
    np.testing.assert_array_equal(model.dists[7], [model.fg_dist[7], model.bg_dist[7]])


def frame_and_lines(model, rng):
    cells = rng.integers(0, 64, (300, 420)).astype(np.int32)
    frame = CellImage(cells, 150, 70)  # a region of the image: lines also run off it
    R, t = pose(rng)
    return frame, project_lines(model, R, t, K, SHAPE)


def test_sampled_pixels_are_the_nearest_to_centre_plus_offset_times_normal(model):
    """OpenCV's pixel centres sit at integers: the nearest pixel to x is floor(x + 0.5) (flooring x alone read every
    sample half a pixel up and left, and moved region's answers by ~0.4 px on exactly rendered frames)."""
    rng = np.random.default_rng(2)
    for _ in range(10):
        frame, lines = frame_and_lines(model, rng)
        offsets = np.sort(rng.uniform(-40, 40, 24))
        cells, inside = corr.sample_pixels(frame, lines, offsets)
        x = np.floor(lines.centers[:, :1] + offsets * lines.normals[:, :1] + 0.5).astype(int) - frame.x0
        y = np.floor(lines.centers[:, 1:] + offsets * lines.normals[:, 1:] + 0.5).astype(int) - frame.y0
        h, w = frame.cells.shape
        want_inside = (x >= 0) & (x < w) & (y >= 0) & (y < h)
        np.testing.assert_array_equal(inside, want_inside)
        assert 0 < want_inside.mean() < 1  # both kinds were tried
        np.testing.assert_array_equal(cells[inside], frame.cells[y[inside], x[inside]])


def plain_contour(frame, logits, lines, scale, cfg):
    """The contour likelihood as first written: a line a row, float64 sums of float32 logs."""
    H = cfg.half_segments
    seg = np.arange(-H, H) + 0.5
    n = min(scale, cfg.pixels_per_segment)
    sub = (np.arange(n) + 0.5) / n - 0.5
    offsets = ((seg[:, None] + sub[None, :]) * scale).ravel()
    cells, inside = corr.sample_pixels(frame, lines, offsets)
    usable = inside & (offsets[None, :] > -lines.fg_px[:, None]) & (offsets[None, :] < lines.bg_px[:, None])
    logit = np.where(usable, logits[cells], 0.0).reshape(len(lines.centers), 2 * H, n).sum(axis=2) * (scale / n)
    p_seg = (1.0 / (1.0 + np.exp(-np.clip(logit, -30, 30)))).astype(np.float32)
    D = H - 2
    d = np.arange(-D, D + 1, dtype=float)
    hf = 0.5 - cfg.amplitude * np.tanh((seg[None, :] - d[:, None]) / (2 * cfg.slope))
    stay, flip = (1 - hf).astype(np.float32), (2 * hf - 1).astype(np.float32)
    ll = np.log(stay[None] + flip[None] * p_seg[:, None, :]).sum(axis=2, dtype=np.float64)
    prob = np.exp(ll - ll.max(axis=1, keepdims=True))
    prob /= prob.sum(axis=1, keepdims=True)
    mean = prob @ d
    var = prob @ d**2 - mean**2
    lean = p_seg - 0.5
    informative = (lean[:, :H].sum(axis=1) > 0) & (lean[:, H:].sum(axis=1) < 0) & (np.abs(mean) < D - 0.5)
    return mean * scale, np.maximum(var * scale**2, cfg.min_variance_px2), informative


@pytest.mark.parametrize("half_segments", [8, 5, 11])
def test_the_contour_likelihood_is_the_plain_formulas_with_the_same_informative_lines(model, half_segments):
    """Logits from a clipped table, as the estimator's are: their sums often cancel exactly, and then only numpy's
    own summation order gives the same informative test."""
    rng = np.random.default_rng(3)
    cfg = LineModel(half_segments=half_segments)
    table = np.log(49.0) * rng.choice([-1.0, -0.5, 0.0, 0.5, 1.0], 64)
    for _ in range(6):
        frame, lines = frame_and_lines(model, rng)
        for scale in (6, 4, 2, 1):
            mean, var, informative = contour_distributions(frame, table, lines, scale, cfg)
            want_mean, want_var, want_informative = plain_contour(frame, table, lines, scale, cfg)
            np.testing.assert_array_equal(informative, want_informative)
            np.testing.assert_allclose(mean, want_mean, atol=1e-4 * scale)
            np.testing.assert_allclose(var, want_var, rtol=1e-4, atol=1e-4)


def test_the_run_sums_add_in_numpys_order():
    rng = np.random.default_rng(4)
    for n in (3, 7, 8, 9, 16, 21):
        x = rng.choice(np.float32([0.48, -0.48, 0.3, -0.3, 0.0, 0.123, -0.4999999]), (200, 2 * n))
        got = corr._run_sums(np.ascontiguousarray(x.T).reshape(2, n, -1))
        np.testing.assert_array_equal(got, [x[:, :n].sum(axis=1), x[:, n:].sum(axis=1)])


def test_the_jacobian_is_the_projections_derivative(model):
    """Finite differences of a line's centre along its normal under R <- Exp(d) R, t <- t + d."""
    rng = np.random.default_rng(5)
    R, t = pose(rng)
    lines = project_lines(model, R, t, K, SHAPE)
    J = line_jacobians(lines, K, t)
    view = model.closest_view(R, t)
    keep = [int(np.argmin(np.linalg.norm(model.points[view] @ R.T + t - p, axis=1))) for p in lines.points_C]
    eps = 1e-7
    for k in range(6):
        d = np.zeros(6)
        d[k] = eps
        R2, t2 = so3.exp(d[:3]) @ R, t + d[3:]
        P = model.points[view][keep] @ R2.T + t2
        uv = np.column_stack([K[0, 0] * P[:, 0] / P[:, 2] + K[0, 2], K[1, 1] * P[:, 1] / P[:, 2] + K[1, 2]])
        np.testing.assert_allclose(((uv - lines.centers) * lines.normals).sum(axis=1) / eps, J[k], rtol=1e-4,
                                   atol=1e-3)


def test_histogram_cells_and_posteriors_are_the_plain_formulas():
    rng = np.random.default_rng(6)
    hist = ColourHistograms(bins=16)
    image = rng.integers(0, 256, (90, 120, 3), dtype=np.uint8)
    c = image.astype(np.int32) >> 4
    cells = hist.index(image[5:80, 7:111])
    np.testing.assert_array_equal(cells, ((c[..., 0] * 16 + c[..., 1]) * 16 + c[..., 2])[5:80, 7:111])
    hist.update(cells[:30].ravel(), cells[30:].ravel())
    many, few = cells.ravel(), cells.ravel()[:100]  # by the whole table, and cell by cell
    for picked in (many, few):
        f, b = hist.fg[picked], hist.bg[picked]
        np.testing.assert_array_equal(hist.posterior(picked), (f + 1e-9) / (f + b + 2e-9))


def test_the_pose_error_keeps_tiny_rotations():
    """The Newton steps' prior term reads the pose's distance from the prior; a rotation log that lost small angles
    (OpenCV's takes the angle from its cosine: 1e-8 rad off, and none under 1e-5 rad) moved LM-O answers by up to
    0.4 px."""
    rng = np.random.default_rng(7)
    R, t = pose(rng)
    for angle in (1e-9, 1e-6, 3e-5, 1e-3, 0.1):
        v = rng.normal(0, 1, 3)
        v *= angle / np.linalg.norm(v)
        e = pose_error(so3.exp(v) @ R, t + [0.001, 0, 0], R, t)
        np.testing.assert_allclose(e[:3], v, rtol=1e-7, atol=1e-15)
        np.testing.assert_allclose(e[3:], [0.001, 0, 0])


def test_the_edge_colours_are_the_nearest_pixels_with_the_border_replicated():
    """`edge_weighted` reads the pixel nearest to each point (floor(x + 0.5), as `sample_pixels`), the region's
    border standing in for whatever lies beyond it."""
    rng = np.random.default_rng(6)
    pixels = rng.integers(0, 256, (90, 120, 3)).astype(np.uint8)
    frame = CellImage(np.zeros((90, 120), np.int32), 200, 100, pixels)
    points = rng.uniform([180, 80], [340, 210], (500, 2))  # inside the region and beyond each side
    x = np.clip(np.floor(points[:, 0] + 0.5).astype(int) - 200, 0, 119)
    y = np.clip(np.floor(points[:, 1] + 0.5).astype(int) - 100, 0, 89)
    assert ((x == 0) | (x == 119)).any() and ((y == 0) | (y == 89)).any()  # the border was read beyond the region
    np.testing.assert_array_equal(corr._colours_at(frame, points), pixels[y, x].astype(np.float32))


def test_a_contour_estimate_on_no_edge_is_less_sure():
    """Lines across a sharp colour step keep their variance within a few per cent; the same lines on a flat patch
    have it grown (1 + (edge_step / s)^2, s -> 0: by orders of magnitude); off (edge_step 0), nothing changes; the
    coarse scales are left alone."""
    pixels = np.full((100, 100, 3), 60, np.uint8)
    pixels[:, 50:] = 200  # a vertical edge between x = 49 and 50 (region coordinates)
    frame = CellImage(np.zeros((100, 100), np.int32), 0, 0, pixels)
    m = 20
    lines = Lines(np.column_stack([np.full(m, 49.5), np.linspace(20, 80, m)]), np.tile([1.0, 0.0], (m, 1)),
                  np.zeros((m, 3)), np.full(m, 30.0), np.full(m, 30.0))
    var = np.full(m, 0.5)
    cfg = LineModel()
    on_edge = corr.edge_weighted(frame, lines, np.zeros(m), var, 1, cfg)
    flat = corr.edge_weighted(frame, lines, np.full(m, -20.0), var, 1, cfg)  # estimates 20 px inside: no step
    assert np.all(on_edge < 1.2 * var) and np.all(flat > 100 * var)
    np.testing.assert_array_equal(corr.edge_weighted(frame, lines, np.full(m, -20.0), var, 1,
                                                     LineModel(edge_step=0.0)), var)
    np.testing.assert_array_equal(corr.edge_weighted(frame, lines, np.full(m, -20.0), var, 4, cfg), var)
