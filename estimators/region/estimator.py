"""The `region` estimator: the pose refined from the request's prior on the object's outline in the
image, with nothing but the object's mesh and colour statistics learned online (SRT3D-style; see
docs/region.md). A request without a prior is refused (InvalidInput): the `chained` kind answers
those with a global estimator.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import trimesh

from estimators.base import EstimateInput, EstimateOutput, Estimator, InvalidInput, Status
from estimators.region.correspondence import LineModel, project_lines, sample_pixels
from estimators.region.histograms import ColourHistograms
from estimators.region.optimizer import OptimizerConfig, optimize
from estimators.region.session_store import SessionStore
from estimators.region.viewpoint_model import ViewpointModel, cached_viewpoint_model

PARAMS = {"scales", "iterations_per_scale", "half_segments", "line_weight", "damping_rotation",
          "damping_translation", "covariance_inflation", "default_prior_sigma_m", "default_prior_sigma_deg",
          "bins", "learning_rate", "max_sessions", "max_session_age_s", "views_subdivisions", "contour_points",
          "cache_dir", "min_confidence", "histogram_px", "refit_scales", "refits", "histogram_init", "margin_factor", "model_colour_weight", "session_weight"}


class RegionEstimator(Estimator):
    kind = "region"
    version = "1"
    uses_image = True
    description = "prior-guided region-based refinement (correspondence lines, colour histograms)"

    def __init__(self, name: str, objects: dict, *, optimizer: OptimizerConfig | None = None,
                 default_prior_sigma_m: float = 0.02, default_prior_sigma_deg: float = 10.0, bins: int = 16,
                 learning_rate: float = 0.2, max_sessions: int = 1024, max_session_age_s: float = 600.0,
                 views_subdivisions: int = 4, contour_points: int = 200, cache_dir: str | Path | None = None,
                 min_confidence: float = 0.3, histogram_px: int = 20, refit_scales: tuple[int, ...] = (2, 1),
                 refits: int = 1, histogram_init: str = "lines", margin_factor: float = 0.5,
                 model_colour_weight: float = 0.0, session_weight: float = 0.5):
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
        self.histogram_px = histogram_px
        self.refit_scales = tuple(refit_scales)
        self.refits = refits
        if histogram_init not in ("region", "lines"):
            raise ValueError(f"histogram_init is 'region' or 'lines', not {histogram_init!r}")
        self.histogram_init = histogram_init
        self.margin_factor = margin_factor
        self._models: dict[str, ViewpointModel] = {}
        self._colours: dict[str, np.ndarray | None] = {}
        self.model_colour_weight = model_colour_weight
        self.session_weight = session_weight
        self.sessions: SessionStore[ColourHistograms] = SessionStore(
            lambda: ColourHistograms(bins, learning_rate, learning_rate), max_sessions, max_session_age_s)

    @classmethod
    def from_spec(cls, spec) -> RegionEstimator:
        spec.check_params(PARAMS)
        p = dict(spec.params)
        ids = spec.object_ids or spec.objects.ids()
        line = LineModel(half_segments=int(p.pop("half_segments", LineModel.half_segments)))
        opt = OptimizerConfig(line_model=line, **{k: p.pop(k) for k in list(p) if k in {
            "iterations_per_scale", "line_weight", "damping_rotation", "damping_translation", "covariance_inflation"}})
        if "scales" in p:
            opt = replace(opt, scales=tuple(int(s) for s in p.pop("scales")))
        if "cache_dir" in p:
            p["cache_dir"] = spec.path(p["cache_dir"])
        return cls(spec.name, {i: spec.objects.get(i) for i in ids}, optimizer=opt, **p)

    def _radius(self, object_id: str) -> float:
        return 0.5 * self._objects[object_id].diameter_m

    def model_colours(self, object_id: str) -> np.ndarray | None:
        """The mesh's vertex colours (N, 3) uint8 RGB, or None when it has none (read once)."""
        if object_id not in self._colours:
            colours = None
            try:
                mesh = trimesh.load(self._objects[object_id].model_path, process=False, force="mesh")
                visual = getattr(mesh, "visual", None)
                if getattr(visual, "kind", None) == "vertex":
                    colours = np.asarray(visual.vertex_colors)[:, :3].astype(np.uint8)
                    if np.all(colours == colours[0]):
                        colours = None  # one colour everywhere: trimesh's default, no information
            except (OSError, ValueError):
                colours = None
            self._colours[object_id] = colours
        return self._colours[object_id]

    def viewpoint_model(self, object_id: str) -> ViewpointModel:
        """Built on first use (or read from the disk cache), then kept."""
        if object_id not in self._models:
            obj = self._objects[object_id]
            if len(obj.faces) == 0:
                raise InvalidInput(f"object '{object_id}' has no mesh faces; the region estimator needs them")
            self._models[object_id] = cached_viewpoint_model(obj.vertices, obj.faces, self.cache_dir,
                                                             **self.view_options)
        return self._models[object_id]

    def _histogram_samples(self, image: np.ndarray, lines, margin_px: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Colours inside and outside the outline, from `margin_px` off it (the pose's uncertainty) to
        `histogram_px` beyond that; inside, short of the object's far side."""
        offsets = margin_px + np.arange(0, self.histogram_px, dtype=float)
        fg, fg_in = sample_pixels(image, lines, -offsets)
        bg, bg_in = sample_pixels(image, lines, offsets)
        deep = np.maximum(0.8 * lines.fg_px, np.minimum(margin_px + 2.0, 0.5 * lines.fg_px))
        fg_in &= offsets[None, :] < deep[:, None]
        bg_in &= offsets[None, :] < 0.8 * lines.bg_px[:, None] + margin_px
        return fg[fg_in], bg[bg_in]

    def _region_samples(self, image: np.ndarray, lines, margin_px: float) -> tuple[np.ndarray, np.ndarray]:
        """Colours of the whole silhouette (the projected outline's polygon) shrunk by `margin_px`, and
        of a ring `histogram_px` wide around it grown by `margin_px`; lines' samples when too small."""
        h, w = image.shape[:2]
        m = int(np.ceil(margin_px)) + self.histogram_px + 2
        lo = np.maximum(np.floor(lines.centers.min(axis=0)).astype(int) - m, 0)
        hi = np.minimum(np.ceil(lines.centers.max(axis=0)).astype(int) + m, [w - 1, h - 1])
        size = hi - lo + 1
        mask = np.zeros((size[1], size[0]), np.uint8)
        cv2.fillPoly(mask, [np.round((lines.centers - lo) * 16).astype(np.int32)], 1, cv2.LINE_8, shift=4)
        dist_in = cv2.distanceTransform(mask, cv2.DIST_L2, 3)
        dist_out = cv2.distanceTransform(1 - mask, cv2.DIST_L2, 3)
        crop = image[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1]
        fg = crop[dist_in > margin_px]
        bg = crop[(dist_out > margin_px) & (dist_out <= margin_px + self.histogram_px)]
        if len(fg) < 50:
            return self._histogram_samples(image, lines, margin_px)
        return fg, bg

    def _prior_px(self, K: np.ndarray, t: np.ndarray, covariance: np.ndarray, radius_m: float) -> float:
        """About how far (px, one sigma) the prior's outline may lie from the object's."""
        f = np.sqrt(K[0, 0] * K[1, 1]) / max(t[2], 1e-3)
        sigma = np.sqrt(np.maximum(np.diag(covariance), 0.0))
        return float(f * (np.hypot(sigma[3], sigma[4]) + radius_m * np.hypot(sigma[0], sigma[1])))

    def _confidence(self, image: np.ndarray, hist: ColourHistograms, lines) -> float:
        """How well the colours agree with the outline: mean foreground posterior a few px inside minus
        a few px outside, over the lines (0: no agreement, 1: perfect)."""
        offsets = np.arange(1, 5, dtype=float)
        fg, fg_in = sample_pixels(image, lines, -offsets + 0.5)
        bg, bg_in = sample_pixels(image, lines, offsets + 0.5)
        pf = hist.posterior(hist.index(fg))
        pb = hist.posterior(hist.index(bg))
        if not fg_in.any() or not bg_in.any():
            return 0.0
        return float(np.clip(pf[fg_in].mean() - pb[bg_in].mean(), 0.0, 1.0))

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
        # This frame's own histograms: from the prior's outline, off it by the prior's uncertainty, a
        # first fit, then histograms again from the fitted outline and the fine scales again (EM-like).
        # A session's histograms, learned on its earlier frames, are mixed in with `session_weight`.
        lines = project_lines(model, R0, t0, K, image.shape[:2])
        if lines is None:
            return EstimateOutput.not_found("the prior puts the object out of view")
        margin = float(np.clip(self.margin_factor * self._prior_px(K, t0, cov, self._radius(object_id)), 1.0,
                               self.histogram_px))
        sampler = self._region_samples if self.histogram_init == "region" else self._histogram_samples

        def frame_histograms(lines, margin):
            own = ColourHistograms(self.bins, self.learning_rate, self.learning_rate)
            own.update(*sampler(image, lines, margin))
            colours = self.model_colours(object_id) if self.model_colour_weight > 0 else None
            if colours is not None:  # the mesh's own colours as part of the foreground model
                own.blend_foreground(colours, self.model_colour_weight)
            return own.mixed(hist, self.session_weight) if hist.initialised else own

        work = frame_histograms(lines, margin)
        result = optimize(image, K, model, work, R0, t0, information, self.optimizer)
        for _ in range(self.refits):
            lines = None if result is None else project_lines(model, result.R, result.t, K, image.shape[:2])
            if lines is None:
                break
            work = frame_histograms(lines, 1.0)
            result = optimize(image, K, model, work, R0, t0, information, self.optimizer,
                              start=(result.R, result.t), scales=self.refit_scales) or result
        stage["optimize"] = (time.perf_counter() - t_opt) * 1e3
        if result is None or result.last_lines is None:
            return EstimateOutput.not_found("the object's outline is out of view at the prior pose")
        lines = project_lines(model, result.R, result.t, K, image.shape[:2])
        if lines is None:
            return EstimateOutput.not_found("the refined pose puts the object out of view")
        confidence = self._confidence(image, work, lines)
        if confidence >= self.min_confidence:
            hist.update(*self._histogram_samples(image, lines))
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = result.R, result.t
        stage["total"] = (time.perf_counter() - start) * 1e3
        message = "" if not fresh else "new session: colour histograms started from the prior"
        if confidence < self.min_confidence:
            return EstimateOutput(Status.OBJECT_NOT_FOUND, message=f"the colours do not fit the outline "
                                  f"(confidence {confidence:.2f} < {self.min_confidence})", confidence=confidence,
                                  stage_ms=stage)
        return EstimateOutput(Status.OK, T, confidence, result.covariance, message, stage)
