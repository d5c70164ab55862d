"""The `region` estimator: the pose refined from the request's prior on the object's outline in the
image, with nothing but the object's mesh and colour statistics learned online (SRT3D-style; see
docs/region.md). A request without a prior is refused (InvalidInput): the `chained` kind answers
those with a global estimator.
"""

from __future__ import annotations

import functools
import threading
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np

from estimators.base import EstimateInput, EstimateOutput, Estimator, InvalidInput, Status
from estimators.region.correspondence import CellImage, LineModel, project_lines, sample_pixels
from estimators.region.histograms import ColourHistograms
from estimators.region.optimizer import OptimizerConfig, answer_covariance, optimize, pose_error
from estimators.region.viewpoint_model import ViewpointModel, cached_viewpoint_model
from estimators.session_store import SessionStore
from flextrack.geometry import se3, so3

PARAMS = {"scales", "iterations_per_scale", "coarse_iterations", "half_segments", "edge_step", "line_weight", "damping_rotation",
          "damping_translation", "covariance_inflation", "inflation_by_confidence", "default_prior_sigma_m", "default_prior_sigma_deg",
          "bins", "learning_rate", "max_sessions", "max_session_age_s", "views_subdivisions", "contour_points",
          "cache_dir", "min_confidence", "min_confidence_coarse", "histogram_px", "refit_scales", "refits", "margin_factors", "session_weight",
          "retry_below", "retry_margin_factors", "coarse_search", "unmix",
          "refit_unmix", "multi_start_deg", "multi_start_sigmas", "flip_check", "flip_margin",
          "flip_check_below", "max_prior_nis"}


class RegionEstimator(Estimator):
    kind = "region"
    version = "1"
    uses_image = True
    needs_prior = True
    description = "prior-guided region-based refinement (correspondence lines, colour histograms)"

    def __init__(self, name: str, objects: dict, *, optimizer: OptimizerConfig | None = None,
                 default_prior_sigma_m: float = 0.02, default_prior_sigma_deg: float = 10.0, bins: int = 16,
                 learning_rate: float = 0.2, max_sessions: int = 1024, max_session_age_s: float = 600.0,
                 views_subdivisions: int = 4, contour_points: int = 200, cache_dir: str | Path | None = None,
                 min_confidence: float = 0.3, min_confidence_coarse: float = 0.45, histogram_px: int = 20, refit_scales: tuple[int, ...] = (1,),
                 refits: int = 1, margin_factors: tuple[float, float] = (0.5, 0.5), session_weight: float = 0.5,
                 retry_below: float = 0.45, retry_margin_factors: tuple[float, float] | None = (1.0, 2.0),
                 coarse_search: bool = True, unmix: float = 0.3, refit_unmix: float = 0.15,
                 multi_start_deg: float = 8.0, multi_start_sigmas: float = 1.0, flip_check: bool = True,
                 flip_margin: float = 0.05, flip_check_below: float = 1.2, max_prior_nis: float = 16.8):
        """`objects`: object id -> ObjectModel (estimators.objects)."""
        super().__init__(name, list(objects))
        self._objects = dict(objects)
        self.optimizer = optimizer or OptimizerConfig()
        self.default_prior_covariance = np.diag([np.radians(default_prior_sigma_deg) ** 2] * 3
                                                + [default_prior_sigma_m**2] * 3)
        self.bins = bins
        self.learning_rate = learning_rate
        self.view_options = {"subdivisions": views_subdivisions, "n_points": contour_points}
        self.cache_dir = Path(cache_dir) if cache_dir else None
        self.min_confidence = min_confidence
        self.min_confidence_coarse = max(min_confidence, min_confidence_coarse)
        self.histogram_px = histogram_px
        self.refit_scales = tuple(refit_scales)
        self.refits = refits
        self.margin_factors = tuple(margin_factors)
        self.retry_below = retry_below
        self.retry_margin_factors = tuple(retry_margin_factors) if retry_margin_factors else None
        self.session_weight = session_weight
        self.coarse_search = coarse_search
        self.unmix, self.refit_unmix = unmix, refit_unmix
        self.multi_start_deg, self.multi_start_sigmas = multi_start_deg, multi_start_sigmas
        self.flip_check, self.flip_margin, self.flip_check_below = flip_check, flip_margin, flip_check_below
        self.max_prior_nis = max_prior_nis
        self._models: dict[str, ViewpointModel] = {}
        self._models_lock = threading.Lock()
        self.sessions: SessionStore[ColourHistograms] = SessionStore(
            lambda: ColourHistograms(bins, learning_rate, learning_rate), max_sessions, max_session_age_s)

    @classmethod
    def from_spec(cls, spec) -> RegionEstimator:
        spec.check_params(PARAMS)
        p = dict(spec.params)
        ids = spec.object_ids or spec.objects.ids()
        line = LineModel(half_segments=int(p.pop("half_segments", LineModel.half_segments)),
                         edge_step=float(p.pop("edge_step", LineModel.edge_step)))
        opt = OptimizerConfig(line_model=line, **{k: p.pop(k) for k in list(p) if k in {
            "iterations_per_scale", "coarse_iterations", "line_weight", "damping_rotation", "damping_translation",
            "covariance_inflation"}})
        if "inflation_by_confidence" in p:
            opt = replace(opt, inflation_by_confidence=tuple(tuple(float(v) for v in knot)
                                                             for knot in p.pop("inflation_by_confidence")))
        if "scales" in p:
            opt = replace(opt, scales=tuple(int(s) for s in p.pop("scales")))
        if "cache_dir" in p:
            p["cache_dir"] = spec.path(p["cache_dir"])
        return cls(spec.name, {i: spec.objects.get(i) for i in ids}, optimizer=opt, **p)

    def _radius(self, object_id: str) -> float:
        return 0.5 * self._objects[object_id].diameter_m

    def viewpoint_model(self, object_id: str) -> ViewpointModel:
        """Built on first use (or read from the disk cache), then kept; once, whatever the threads."""
        with self._models_lock:
            if object_id not in self._models:
                obj = self._objects[object_id]
                if len(obj.faces) == 0:
                    raise InvalidInput(f"object '{object_id}' has no mesh faces; the region estimator needs them")
                self._models[object_id] = cached_viewpoint_model(obj.vertices, obj.faces, self.cache_dir,
                                                                 **self.view_options)
            return self._models[object_id]

    def _histogram_samples(self, frame: CellImage, lines, margin_fg: float = 1.0,
                           margin_bg: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Colours along the lines inside the outline from `margin_fg` and outside from `margin_bg` off it
        (the pose's uncertainty), `histogram_px` deep; inside, short of the object's far side."""
        depth = np.arange(0, self.histogram_px, dtype=float)
        fg, fg_in = sample_pixels(frame, lines, -(margin_fg + depth))
        bg, bg_in = sample_pixels(frame, lines, margin_bg + depth)
        deep = np.maximum(0.8 * lines.fg_px, np.minimum(margin_fg + 2.0, 0.5 * lines.fg_px))
        fg_in &= (margin_fg + depth)[None, :] < deep[:, None]
        bg_in &= (margin_bg + depth)[None, :] < 0.8 * lines.bg_px[:, None] + margin_bg
        return fg[fg_in], bg[bg_in]

    def _prior_px(self, K: np.ndarray, t: np.ndarray, covariance: np.ndarray, radius_m: float) -> float:
        """About how far (px, one sigma) the prior's outline may lie from the object's."""
        f = np.sqrt(K[0, 0] * K[1, 1]) / max(t[2], 1e-3)
        sigma = np.sqrt(np.maximum(np.diag(covariance), 0.0))
        return float(f * (np.hypot(sigma[3], sigma[4]) + radius_m * np.hypot(sigma[0], sigma[1])))

    def _agreement(self, frame: CellImage, hist: ColourHistograms, lines, agree: float = 0.2) -> tuple[float, float]:
        """How well the colours agree with the outline, from the foreground posteriors 1-4 px inside and outside
        each line (sampled once): the confidence, their mean inside minus outside over all lines (0: none,
        1: perfect), and the support, the share of lines whose own difference is above `agree` (the colours
        step from object to background where the outline says)."""
        offsets = np.arange(1, 5, dtype=float)
        fg, fg_in = sample_pixels(frame, lines, -offsets + 0.5)
        bg, bg_in = sample_pixels(frame, lines, offsets + 0.5)
        if not fg_in.any() or not bg_in.any():
            return 0.0, 0.0
        pf, pb = hist.posterior(fg), hist.posterior(bg)
        confidence = float(np.clip(pf[fg_in].mean() - pb[bg_in].mean(), 0.0, 1.0))
        with np.errstate(invalid="ignore"):
            step = np.nanmean(np.where(fg_in, pf, np.nan), axis=1) - np.nanmean(np.where(bg_in, pb, np.nan), axis=1)
        return confidence, float(np.mean(np.nan_to_num(step, nan=0.0) > agree))

    def _starts(self, R0: np.ndarray, t0: np.ndarray, cov: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Where fits start: the prior's mean, and, when its rotation is unsure by more than `multi_start_deg`
        (a start from a coarse prior: a user lining the phone up with a guide view), the mean turned by one
        sigma either way about each camera axis; the best fit by its own score is kept."""
        sigma = np.sqrt(np.maximum(np.diag(cov)[:3], 0.0))
        starts = [(R0, t0)]
        if np.degrees(sigma.max()) >= self.multi_start_deg:
            for axis in range(3):
                for sign in (-1.0, 1.0):
                    d = np.zeros(3)
                    d[axis] = sign * self.multi_start_sigmas * sigma[axis]
                    starts.append((so3.exp(d) @ R0, t0))
        return starts

    @staticmethod
    def _fits_scatter(fits: list, best) -> np.ndarray:
        """The spread of the frame's other fits about the kept one: the other starts around a coarse prior, or the
        first fit when a retry further off the outline won. Where they end apart the image did not pull them to
        one pose, and the answer is that unsure (zero when one fit ran; docs/region.md: LM-O's mean NEES at
        20 mm / 10 deg about halved)."""
        kept = best[2]
        ends = [fit[2] for fit in fits if fit is not best and fit[2] is not None]
        if not ends:
            return np.zeros((6, 6))
        e = np.array([pose_error(end.R, end.t, kept.R, kept.t) for end in ends])
        return e.T @ e / len(fits)

    @staticmethod
    def prior_nis(result, R0: np.ndarray, t0: np.ndarray, prior_covariance: np.ndarray,
                  covariance: np.ndarray) -> float:
        """The fit's squared Mahalanobis distance from the prior under both covariances (a filter's innovation test,
        chi-square with 6 dof where both are honest). Over `max_prior_nis` (16.8: the 99 % point) the answer and
        the prior contradict each other, and one of them is wrong: on LM-O mostly fits that drifted onto something
        else where the object is barely visible (docs/region.md)."""
        innovation = pose_error(result.R, result.t, R0, t0)
        return float(innovation @ np.linalg.solve(prior_covariance + covariance, innovation))

    def _symmetric(self, object_id: str, a, b, tolerance_deg: float = 10.0) -> bool:
        """Whether two fitted poses are one another up to one of the object's symmetries (models_info.json): then
        the turned prior fitting as well says nothing against the answer."""
        if a is None or b is None:
            return False
        S = np.asarray(getattr(self._objects[object_id], "symmetries", np.eye(4)[None]), float)[:, :3, :3]
        relative = np.einsum("ij,sjk->sik", b.R.T @ a.R, np.transpose(S, (0, 2, 1)))  # (R_b S)^T R_a per S
        cos = (np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0
        return bool(np.any(cos > np.cos(np.radians(tolerance_deg))))

    def _coarse_shift(self, frame: CellImage, hist: ColourHistograms, lines, prior_px: float, K: np.ndarray,
                      t0: np.ndarray) -> np.ndarray:
        """A translation (camera frame, m) moving the prior's silhouette, in the image plane, to where
        the colours agree with it best within +-2.5 sigma_px: the sum of (2 p_fg - 1) over the shifted
        silhouette, for every shift at once (a correlation)."""
        reach = int(np.clip(2.5 * prior_px, 2, 60))
        poly = lines.centers - [frame.x0, frame.y0]
        lo = np.floor(poly.min(axis=0)).astype(int)
        size = np.ceil(poly.max(axis=0)).astype(int) - lo + 1
        if np.any(size < 4):
            return np.zeros(3)
        template = np.zeros((size[1], size[0]), np.float32)
        cv2.fillPoly(template, [np.round((poly - lo) * 16).astype(np.int32)], 1.0, cv2.LINE_8, shift=4)
        # the window of shifts: the template's top-left corner from lo - reach to lo + reach (off the region: no
        # evidence either way)
        x0, y0 = lo - reach
        window = np.zeros((size[1] + 2 * reach, size[0] + 2 * reach), np.float32)
        h, w = frame.cells.shape
        ya, yb, xa, xb = max(y0, 0), min(y0 + window.shape[0], h), max(x0, 0), min(x0 + window.shape[1], w)
        if ya < yb and xa < xb:
            window[ya - y0:yb - y0, xa - x0:xb - x0] = hist.scores(frame.cells[ya:yb, xa:xb])
        response = cv2.matchTemplate(window, template, cv2.TM_CCORR)
        dy, dx = np.unravel_index(int(np.argmax(response)), response.shape)
        shift_px = np.array([dx - reach, dy - reach], dtype=float)
        return np.array([shift_px[0] * t0[2] / K[0, 0], shift_px[1] * t0[2] / K[1, 1], 0.0])

    def _first_colour_outline(self, model: ViewpointModel, K: np.ndarray, shape: tuple[int, int], prior_lines,
                              margins: list[float]) -> tuple:
        """Where a fit's first colours are learned: (lines, (margin inside, margin outside)), the start's outline
        that far off it. (`flextrack evaluate prior --colours-at-truth` learns them at the true outline instead, to
        measure what the colour model costs.)"""
        return prior_lines, margins

    def _fit(self, frame, shape, K, model, hist, R0, t0, information, prior_px, margin_factors, start=None,
             prior_at_start: bool = False):
        """(score, confidence, result, lines at the result): this frame's own histograms from the outline at
        `start` (default: the prior's), `margin_factors` x the prior's pixel uncertainty off it (inside,
        outside), a first fit from there, then histograms again from the fitted outline and the fine scales
        again (EM-like). A session's histograms, learned on its earlier frames, are mixed in with
        `session_weight`. The score (colour agreement plus the share of lines that agree) ranks fits from
        different starts."""
        def frame_histograms(lines, margins, unmix=0.0):
            own = ColourHistograms(self.bins, self.learning_rate, self.learning_rate)
            own.update(*self._histogram_samples(frame, lines, *margins))
            own = own.unmixed(unmix)
            return own.mixed(hist, self.session_weight) if hist.initialised else own

        margins = [float(np.clip(f * prior_px, 1.0, 3.0 * self.histogram_px)) for f in margin_factors]
        R_s, t_s = start or (R0, t0)
        if prior_at_start:  # a hypothesis of its own (the flipped prior): its prior term centred on it
            R0, t0 = R_s, t_s
        prior_lines = project_lines(model, R_s, t_s, K, shape)
        if prior_lines is None:
            return -1.0, -1.0, None, None
        work = frame_histograms(*self._first_colour_outline(model, K, shape, prior_lines, margins), self.unmix)
        start = (R_s, t_s)
        if self.coarse_search:
            start = (R_s, t_s + self._coarse_shift(frame, work, prior_lines, prior_px, K, t_s))
        result = optimize(frame, K, model, work, R0, t0, information, self.optimizer, shape=shape, start=start)
        for _ in range(self.refits):
            lines = None if result is None else project_lines(model, result.R, result.t, K, shape)
            if lines is None:
                break
            work = frame_histograms(lines, (1.0, 1.0), self.refit_unmix)
            result = optimize(frame, K, model, work, R0, t0, information, self.optimizer,
                              start=(result.R, result.t), scales=self.refit_scales, shape=shape) or result
        lines = None if result is None else project_lines(model, result.R, result.t, K, shape)
        if lines is None:
            return -1.0, -1.0, None, None
        confidence, support = self._agreement(frame, work, lines)
        return confidence + support, confidence, result, lines

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        start = time.perf_counter()
        object_id = self.resolve_object(inp.object_id)
        if inp.prior_T_CO is None:
            raise InvalidInput(f"estimator '{self.name}' refines a prior pose: send EstimateRequest.prior "
                               "(or ask a 'chained' estimator, which answers without one)")
        if inp.camera is None or inp.image is None:
            raise InvalidInput(f"estimator '{self.name}' needs intrinsics and an image")
        image = inp.image if inp.image.ndim == 3 else np.repeat(inp.image[..., None], 3, axis=2)
        K = inp.camera.K
        if any(inp.camera.distortion):  # the lines are projected by a pinhole: take the lens out of the image
            image = cv2.remap(image, *_undistortion_maps(tuple(K.ravel()), inp.camera.distortion, image.shape[:2]),
                              cv2.INTER_LINEAR)
        cov = inp.prior_covariance if inp.prior_covariance is not None else self.default_prior_covariance
        information = np.linalg.inv(cov)
        R0, t0 = inp.prior_T_CO[:3, :3], inp.prior_T_CO[:3, 3]
        model = self.viewpoint_model(object_id)
        if inp.session_id:
            hist, fresh = self.sessions.get((inp.session_id, object_id))
        else:
            hist, fresh = ColourHistograms(self.bins, self.learning_rate, self.learning_rate), True
        stage = {"setup": (time.perf_counter() - start) * 1e3}
        t_opt = time.perf_counter()
        shape = image.shape[:2]
        lines = project_lines(model, R0, t0, K, shape)
        if lines is None:
            return EstimateOutput.not_found("the prior puts the object out of view")
        prior_px = self._prior_px(K, t0, cov, self._radius(object_id))
        # the pixels as histogram cells, once, as far around the prior's outline as any line may reach
        reach = max(self.optimizer.scales) * self.optimizer.line_model.half_segments
        frame = CellImage.around(image, hist, lines.centers, reach + 3 * prior_px + 2 * self.histogram_px)
        starts = self._starts(R0, t0, cov)
        fits = [self._fit(frame, shape, K, model, hist, R0, t0, information, prior_px, self.margin_factors, s)
                for s in starts]
        # from a coarse prior a weak fit is as often far off as near: it is refused, not answered (docs/region.md)
        coarse = len(starts) > 1
        needed = self.min_confidence_coarse if coarse else self.min_confidence
        best = max(fits, key=lambda fit: fit[0])
        if best[1] < self.retry_below and self.retry_margin_factors:
            # lost, most likely from histograms learned off the prior's outline: again, further off it
            other = self._fit(frame, shape, K, model, hist, R0, t0, information, prior_px,
                              self.retry_margin_factors)
            best = max(best, other, key=lambda fit: fit[0])
        score, confidence, result, lines = best
        if result is not None and confidence >= needed and self.flip_check \
                and (fresh or score < self.flip_check_below):
            flip_T = se3.turned_about_line_of_sight(inp.prior_T_CO, model.center)
            flip = (flip_T[:3, :3], flip_T[:3, 3])
            alt = self._fit(frame, shape, K, model, hist, R0, t0, information, prior_px, self.margin_factors, flip,
                            prior_at_start=True)
            if alt[0] >= score - self.flip_margin and not self._symmetric(object_id, alt[2], result):
                stage["optimize"] = (time.perf_counter() - t_opt) * 1e3
                return EstimateOutput(Status.OBJECT_NOT_FOUND, message=(
                    f"the prior looks wrong for its claimed uncertainty: the pose turned 180 deg about the line of "
                    f"sight fits the image as well (score {alt[0]:.2f} against {score:.2f}); send a prior from "
                    "another source or ask a global estimator"), confidence=confidence, stage_ms=stage)
        stage["optimize"] = (time.perf_counter() - t_opt) * 1e3
        if result is None or lines is None:
            return EstimateOutput.not_found("the object's outline left the image")
        if confidence >= needed:
            hist.update(*self._histogram_samples(frame, lines))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = result.R, result.t
        stage["total"] = (time.perf_counter() - start) * 1e3
        message = "" if not fresh else "new session: colour histograms started from the prior"
        if confidence < needed:
            advice = " needed from a coarse prior: keep lining up" if coarse else ""
            return EstimateOutput(Status.OBJECT_NOT_FOUND, message=f"the colours do not fit the outline "
                                  f"(confidence {confidence:.2f} < {needed}{advice})", confidence=confidence,
                                  stage_ms=stage)
        covariance = answer_covariance(result, self.optimizer, confidence) + self._fits_scatter(fits, best)
        nis = self.prior_nis(result, R0, t0, cov, covariance)
        if nis > self.max_prior_nis:
            return EstimateOutput(Status.OBJECT_NOT_FOUND, message=(
                f"the fit ended where the prior says the object is not: its distance from the prior is {nis:.1f} "
                f"(chi-square, 6 dof) > {self.max_prior_nis}; the prior's covariance is too tight or the fit took "
                "something else for the object"), confidence=confidence, stage_ms=stage)
        return EstimateOutput(Status.OK, T, confidence, covariance, message, stage)


@functools.lru_cache(maxsize=8)
def _undistortion_maps(K: tuple[float, ...], distortion: tuple[float, ...], shape: tuple[int, int]):
    """OpenCV's remap tables from the lens's image to a pinhole one with the same K (cached: a device sends
    the same intrinsics with every frame)."""
    return cv2.initUndistortRectifyMap(np.array(K).reshape(3, 3), np.array(distortion), None,
                                       np.array(K).reshape(3, 3), (shape[1], shape[0]), cv2.CV_16SC2)
