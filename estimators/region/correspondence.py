"""Correspondence lines: the closest view's contour points projected at the current pose, lines
along their normals in the image, the colour posterior sampled along them in segments of `scale`
pixels, and SRT3D's probabilistic model of where on each line the contour lies.

Along a line, positions r (in segments, positive outwards) with foreground posteriors p_r; for a
contour at d the smoothed step h_f(x) = 1/2 - a tanh(x / (2 s)) says how likely a segment x from
the contour is foreground, and the line's likelihood is prod_r h_f(r - d) p_r + (1 - h_f(r - d))
(1 - p_r). Normalised over the candidate d, it gives the contour position's mean and variance,
which the optimizer treats as a Gaussian measurement of the projected contour point.
"""

from __future__ import annotations

import functools
import threading
from dataclasses import dataclass

import numpy as np

from estimators.region.histograms import ColourHistograms
from estimators.region.viewpoint_model import ViewpointModel

PIXEL_CLIP = 0.02  # pixel posteriors kept in [clip, 1 - clip]: a histogram's empty cell is not certainty


@dataclass
class Lines:
    """Arrays of M lines. `project_lines` makes each a view of one (10, M) array (a row a coordinate), so that
    the per-line maths runs along contiguous rows; `.T` of a field is that row block."""

    centers: np.ndarray  # (M, 2) px, the projected contour points
    normals: np.ndarray  # (M, 2) unit, outwards in the image
    points_C: np.ndarray  # (M, 3) m, camera frame
    fg_px: np.ndarray  # (M,) how far inwards the line stays on the object (px)
    bg_px: np.ndarray  # (M,) how far outwards it stays off it (px)


_recent = threading.local()  # this thread's last projections: (model, key, lines)


def project_lines(model: ViewpointModel, R: np.ndarray, t: np.ndarray, K: np.ndarray,
                  shape: tuple[int, int], margin_px: float = 2.0) -> Lines | None:
    """Lines of the view closest to the pose, those with their centre in the image and in front (read-only).

    A fit projects the same pose twice, at the end of one optimisation and the start of the next (and the prior,
    for the estimator and its first fit): the thread's last two projections are kept and given again."""
    key = (R.tobytes(), t.tobytes(), K.tobytes(), tuple(shape), margin_px)
    recent = getattr(_recent, "lines", None) or []
    for entry in recent:
        if entry[0] is model and entry[1] == key:
            return entry[2]
    lines = _project_lines(model, R, t, K, shape, margin_px)
    _recent.lines = [(model, key, lines)] + recent[:1]
    return lines


def _project_lines(model: ViewpointModel, R: np.ndarray, t: np.ndarray, K: np.ndarray,
                   shape: tuple[int, int], margin_px: float) -> Lines | None:
    view = model.closest_view(R, t)
    A = R @ model.stacked[view]  # (3, 2N): the view's points, then its normals, turned into the camera frame
    n = A.shape[1] // 2
    P, nC = A[:, :n], A[:, n:]
    P += t[:, None]
    z = P[2]
    if z.min() <= 1e-3:
        return None
    f = K[:2, :2].diagonal()[:, None]  # fx, fy
    out = np.empty((10, n))  # rows: u, v, normal (2), P (3), fg px, bg px, and a spare for the normal's length
    uv, n2 = out[0:2], out[2:4]
    np.multiply(P[:2], f, out=uv)
    uv /= z
    uv += K[:2, 2:]
    # the 3D normal's image direction: d(uv) along it
    np.multiply(nC[:2], z, out=n2)
    n2 -= P[:2] * nC[2]
    n2 *= f
    n2 /= z * z
    norm = out[9]
    np.hypot(n2[0], n2[1], out=norm)
    h, w = shape
    keep = (uv >= margin_px) & (uv <= np.array([[w - 1 - margin_px], [h - 1 - margin_px]]))
    keep = keep[0] & keep[1] & (norm > 1e-9)
    if np.count_nonzero(keep) < 8:
        return None
    out[4:7] = P
    np.multiply(model.dists[view], np.sqrt(f[0, 0] * f[1, 0]) / z, out=out[7:9])  # m -> px at the point's depth
    out = out.compress(keep, axis=1)  # C-ordered, unlike out[:, keep]: each row stays contiguous
    out[2:4] /= out[9]
    out.flags.writeable = False  # shared by the callers that project the same pose
    return Lines(out[0:2].T, out[2:4].T, out[4:7].T, out[7], out[8])


@dataclass(frozen=True)
class CellImage:
    """The frame's pixels as histogram cells (one int a pixel, computed once a frame) over a region
    of interest; pixels outside it count as off the image."""

    cells: np.ndarray  # (h, w) int32
    x0: int
    y0: int
    pixels: np.ndarray | None = None  # (h, w, 3) uint8: the same region's colours (a view of the frame)

    @classmethod
    def around(cls, image: np.ndarray, hist: ColourHistograms, centers: np.ndarray, pad_px: float) -> CellImage:
        h, w = image.shape[:2]
        x0, y0 = np.maximum(np.floor(centers.min(axis=0) - pad_px).astype(int), 0)
        x1, y1 = np.minimum(np.ceil(centers.max(axis=0) + pad_px).astype(int) + 1, [w, h])
        x0, y0 = min(x0, max(x1 - 1, 0)), min(y0, max(y1 - 1, 0))
        region = np.ascontiguousarray(image[y0:max(y1, y0 + 1), x0:max(x1, x0 + 1)])
        return cls(hist.index(region), int(x0), int(y0), region)


def sample_pixels(frame: CellImage, lines: Lines, offsets_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells (M, S) at the pixels nearest to centre + offset * normal, and which lay in the frame's region
    (a pixel off it reads as some cell of the region: only the mask says which are real)."""
    cells, inside = _sample_rows(frame, lines, offsets_px)
    return cells.T, inside.T


def _sample_rows(frame: CellImage, lines: Lines, offsets_px: np.ndarray,
                 steps: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`sample_pixels` as (S, M): a row an offset, the lines along the rows (`steps`: `_steps(offsets_px)`)."""
    h, w = frame.cells.shape
    s = len(offsets_px)
    steps = _steps(offsets_px) if steps is None else steps
    xy = steps @ np.concatenate([lines.normals.T, lines.centers.T])  # (2S, M): x, then y
    xy += 0.5  # the nearest pixel: OpenCV's pixel centres sit at integers (flooring alone read 0.5 px up-left)
    xy = np.floor(xy, out=xy).astype(np.int32)
    x, y = xy[:s], xy[s:]
    x -= frame.x0
    y -= frame.y0
    inside = (x.view(np.uint32) < w) & (y.view(np.uint32) < h)  # negatives read as huge: one test a side
    y *= w
    y += x
    return frame.cells.ravel().take(y, mode="clip"), inside


def _steps(offsets_px: np.ndarray) -> np.ndarray:
    """(2S, 4): with the lines' rows (normal x, normal y, centre x, centre y) as the right factor, one matrix
    product gives every x = offset * normal x + centre x, then every y (the same sums, rounded the same way: the
    zeros add nothing)."""
    s = len(offsets_px)
    steps = np.zeros((2 * s, 4))
    steps[:s, 0] = steps[s:, 1] = offsets_px
    steps[:s, 2] = steps[s:, 3] = 1.0
    return steps


@dataclass(frozen=True)
class LineModel:
    half_segments: int = 8  # segments on each side of the line's centre
    amplitude: float = 0.43  # SRT3D's smoothed step: h_f(x) = 1/2 - amplitude * tanh(x / (2 slope))
    slope: float = 0.5  # in segments
    min_variance_px2: float = 0.25  # floor of a line's contour-position variance
    pixels_per_segment: int = 2  # pixels sampled per segment (each standing for scale / n of them)
    edge_step: float = 40.0  # a contour estimate on a colour step weaker than this is less sure (0: off; `edge_weighted`)
    edge_scale_px: int = 2  # ... at scales up to this (the fine ones, where the estimate is within a pixel or two)


def contour_distributions(frame: CellImage, logits: np.ndarray, lines: Lines, scale: int,
                          cfg: LineModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per line: the mean (px, along the normal, from the centre) and variance (px^2) of the contour
    position, and whether the line carried information (both colours seen). `logits`: each histogram
    cell's clipped foreground log-odds (`ColourHistograms.logits(PIXEL_CLIP)`)."""
    H = cfg.half_segments
    # each segment is `scale` pixels; its posterior multiplies its pixels' (log-odds summed), of at most
    # `pixels_per_segment` of them spread over it (a coarse segment's every pixel costs time, not accuracy)
    n = min(scale, cfg.pixels_per_segment)
    offsets, steps = _offsets(H, n, scale)
    # (S, M) and (2H, M) below: the lines run along the rows, so that every reduction adds whole rows
    cells, inside = _sample_rows(frame, lines, offsets, steps)
    # pixels beyond the object's other side (inwards) or another part of it (outwards), and off the
    # image, carry nothing
    usable = inside & (offsets[:, None] > -lines.fg_px) & (offsets[:, None] < lines.bg_px)
    logit = np.where(usable, logits.take(cells), 0.0)
    if n == 2:  # the segment's two pixels (rows 2k and 2k + 1)
        logit = logit[0::2] + logit[1::2]
    elif n > 2:
        logit = logit.reshape(2 * H, n, -1).sum(axis=1)
    logit *= -scale / n  # the segments' log-odds, negated for the logistic below
    np.clip(logit, -30, 30, out=logit)
    np.exp(logit, out=logit)
    logit += 1.0
    p_seg = np.reciprocal(logit, out=logit).astype(np.float32)  # (2H, M)
    d_powers, stay, flip = _step_model(H, cfg.amplitude, cfg.slope)
    # log-likelihood of each candidate d: the log of the product over segments of h_f p + (1 - h_f) (1 - p), that
    # is (1 - h_f) + (2 h_f - 1) p, in float32 (each term lies in [0.07, 1]: 2H = 16 of them are at least 3e-19,
    # far from float32's underflow; one log a candidate instead of one a term)
    terms = flip * p_seg  # (2D+1, 2H, M)
    terms += stay
    ll = np.log(terms.prod(axis=1)).astype(np.float64)  # (2D+1, M)
    ll -= ll.max(axis=0)
    prob = np.exp(ll, out=ll)
    prob /= prob.sum(axis=0)
    mean, var = d_powers @ prob  # the first two moments
    var -= mean**2
    # a line carries information when it goes from foreground (inside) to background (outside) and its
    # contour is not pressed against the end of the range; a line across an occluder (background on
    # both sides) or along the object's print (foreground on both) would pull the pose wrongly
    p_seg -= 0.5
    lean = _run_sums(p_seg.reshape(2, H, -1))  # inside, outside
    D = len(d_powers[0]) // 2
    informative = (lean[0] > 0) & (lean[1] < 0) & (np.abs(mean) < D - 0.5)
    var *= scale**2
    mean *= scale
    return mean, np.maximum(var, cfg.min_variance_px2, out=var), informative


def edge_weighted(frame: CellImage, lines: Lines, mean: np.ndarray, var: np.ndarray, scale: int,
                  cfg: LineModel) -> np.ndarray:
    """Each line's variance grown where the frame shows no edge at its contour estimate: times 1 + (edge_step /
    s)^2, s the RGB distance between the pixels 1 px outside and 1 px inside the estimate. The colours say
    roughly where the outline is; a real outline is also a step in the image, and an estimate on none (a
    shaded rim, the background's colours close to the object's) is the one most likely off (docs/region.md:
    on LM-O, 10 mm / 5 deg, 58.0 % -> 62.3 % under 5 px, the held-out odd frames 56.2 % -> 62.3 %). Only at
    scales up to `edge_scale_px`."""
    if cfg.edge_step <= 0 or scale > cfg.edge_scale_px or frame.pixels is None:
        return var
    outside = lines.centers + (mean + 1.0)[:, None] * lines.normals
    inside = lines.centers + (mean - 1.0)[:, None] * lines.normals
    colours = _colours_at(frame, np.concatenate([outside, inside]))  # one read for both
    d = colours[:len(mean)] - colours[len(mean):]
    step2 = np.maximum(np.einsum("ij,ij->i", d, d), 1e-6)
    return var * (1.0 + cfg.edge_step * cfg.edge_step / step2)


def _colours_at(frame: CellImage, points: np.ndarray) -> np.ndarray:
    """The region's colours (M, 3, float32) at the pixels nearest to image points (M, 2) (pixel centres at
    integers, as `sample_pixels`), the region's border replicated beyond it. Nearest, not bilinear: the same
    answers on LM-O (ad hoc, 65.5 / 69.8 % against 65.3 / 69.5 % on the even / odd frames) at half the cost."""
    h, w = frame.pixels.shape[:2]
    x = np.clip(np.floor(points[:, 0] + 0.5).astype(np.intp) - frame.x0, 0, w - 1)
    y = np.clip(np.floor(points[:, 1] + 0.5).astype(np.intp) - frame.y0, 0, h - 1)
    return frame.pixels.reshape(-1, 3).take(y * w + x, axis=0).astype(np.float32)  # a view: `around` keeps it whole


def _run_sums(x: np.ndarray) -> np.ndarray:
    """(2, n, M) -> (2, M): the sums over n, added in the order numpy adds a contiguous run of n <= 128 float32s
    (eight running sums, then in pairs). A line's colour lean is often balanced exactly (clipped posteriors cancel),
    and another order's rounding would then flip its informative test: on LM-O, 14 of 210 answers moved by 0.2 to
    24 px with row-by-row sums."""
    n = x.shape[1]
    if n < 8:
        total = x[:, 0].copy()
        for i in range(1, n):
            total += x[:, i]
        return total
    whole = n - n % 8
    runs = x[:, 0:8].copy()
    for i in range(8, whole, 8):
        runs += x[:, i:i + 8]
    pairs = runs[:, 0::2] + runs[:, 1::2]
    quads = pairs[:, 0::2] + pairs[:, 1::2]
    total = quads[:, 0] + quads[:, 1]
    for i in range(whole, n):
        total += x[:, i]
    return total


@functools.lru_cache(maxsize=32)
def _offsets(half_segments: int, n: int, scale: int) -> tuple[np.ndarray, np.ndarray]:
    """The sampled pixels' offsets along a line (px from its centre): `n` spread over each of the 2 H segments; and
    their `_steps`."""
    seg = np.arange(-half_segments, half_segments) + 0.5  # segment centres, segments
    sub = (np.arange(n) + 0.5) / n - 0.5
    offsets = ((seg[:, None] + sub[None, :]) * scale).ravel()
    steps = _steps(offsets)
    offsets.flags.writeable = steps.flags.writeable = False
    return offsets, steps


@functools.lru_cache(maxsize=8)
def _step_model(half_segments: int, amplitude: float, slope: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The candidate contour positions d (segments, within 2 of the line's ends) and their squares, (2, 2D+1), and,
    per candidate and segment, 1 - h_f and 2 h_f - 1 of SRT3D's smoothed step h_f(x) = 1/2 - amplitude tanh(x /
    (2 slope)), (2D+1, 2H, 1)."""
    seg = np.arange(-half_segments, half_segments) + 0.5
    D = half_segments - 2
    d = np.arange(-D, D + 1, dtype=float)
    hf = 0.5 - amplitude * np.tanh((seg[None, :] - d[:, None]) / (2 * slope))[:, :, None]
    out = np.stack([d, d * d]), (1 - hf).astype(np.float32), (2 * hf - 1).astype(np.float32)
    for a in out:
        a.flags.writeable = False
    return out
