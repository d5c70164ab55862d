"""The `pvnet` estimator: a PVNet-style network (onnxruntime), RANSAC keypoint voting, then PnP.

Per frame: the image is halved (area averaging) and the network predicts the object mask and, per
pixel, unit vectors towards the object's keypoints. The whole-frame searches run the model's int8
copy where it has one (`search_model`; 3.4 times faster on a CPU core, and the search only has
to find the object), the upright crop pass voted on the float model: int8 there moved the poses'
ADD by 1.7 mm on average and cost 2.5 % ADD on the held-out frames (docs/pvnet.md, Speed). The
turned crops, a fallback on the few frames whose upright crop is unsure, run on the int8 copy too
(`turns_on_search_model`). The largest mask component locates the object
(objects that look small there are looked for again at full resolution); a second pass on a crop
scaled so that the object's box is about `zoom_object_px` wide (the sizes it was mostly trained
on, and more pixels on small far objects) gives the field that is voted on; that crop is also
run turned by 90, 180 and 270 degrees (`rotations`), each turn a candidate of its own, for a device
rolled further than the training views were. The 2D keypoints then go through the `pnp`
estimator, the one PnP solver of the project, and the pose is refined on the image's edges
(`refine`, estimators/contour_refine.py): PnP on voted keypoints is right in 2D but a few per cent
off in depth, and the object's outline fixes that.

Every pose carries its covariance (wire convention, flextrack.wire; docs/estimators.md):
- the refined pose: the refinement's Gauss-Newton information J^T J at its solution (contour rows
  and the keypoint prior's), scaled by the contour residual s: Sigma = refine_inflation *
  s^2 (s / 0.35 px)^refine_edge_power (J^T J)^-1. Its errors come mostly from edges that are not
  the outline's (the print, the background), which the iid residuals understate and which grow
  with s faster than s^2;
- PnP's pose (refine = false, or a refinement that kept it): the voted keypoints' spreads C_i
  through PnP's Jacobian, Sigma = keypoint_inflation * (sum_i J_i^T (C_i + floor^2 I)^-1 J_i)^-1.
The inflations are fitted by `flextrack evaluate nees` on tuning frames.

The network is tied to one object: its ONNX metadata holds the 3D keypoints it was trained for,
and loading refuses a model whose keypoints differ from the object's registered ones.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, replace
from dataclasses import fields as dataclass_fields
from pathlib import Path
from typing import NamedTuple

import cv2
import numpy as np

from estimators.base import EstimateInput, EstimateOutput, Estimator, InvalidInput, Status
from estimators.contour_refine import ContourRefiner
from estimators.keypoint_voting import VotingConfig, vote_with_spread
from estimators.objects import ObjectRegistry
from estimators.pnp import PnpEstimator, covariance, pose_jacobian

# The covariance (docs/estimators.md; the inflations fitted by `flextrack evaluate nees` on its tuning frames)
KEYPOINT_FLOOR_PX = 0.3  # px added in quadrature to each voted keypoint's spread
KEYPOINT_INFLATION = 1.70  # PnP's pose (refine = false) from the voted keypoints
REFINE_FLOOR_PX = 0.1  # least RMS contour residual the refinement's covariance assumes
REFINE_EDGE_REF_PX = 0.35  # a typical RMS contour residual: where the edge-quality scaling is 1
REFINE_EDGE_POWER = 4.0  # the variance grows as s^(2 + p) with the RMS contour residual s
REFINE_INFLATION = 25.8  # the refined pose


@dataclass(frozen=True)
class PvnetOptions:
    """The pvnet estimator's settings; a config file's `[estimators.params]` names these fields."""

    min_mask_px: int = 12  # smallest mask component that counts as the object
    zoom: bool = True  # a second pass on a crop scaled to the object
    zoom_size: int = 128  # that crop's side, network input px
    zoom_object_px: float = 64.0  # the object's box width in the crop
    full_resolution_search: bool = True  # look again at full resolution for objects that look small
    search_px: int = 320 * 240  # the whole-frame search's network input has at most this many pixels (a frame
    full_search_px: int = 640 * 480  # larger is reduced more), the far-object search's at most this many: any frame
    # shape then costs at most what a 640x480 one does, in CPU and memory (docs/pvnet.md)
    near_box_px: float = 50.0  # "small": a box under this many frame px
    window_px: int = 160  # a small candidate is searched again in a window of this side around it (0: the whole frame)
    candidates: int = 3  # mask components tried
    candidate_share: float = 0.25  # a component smaller than this share of the largest is not tried
    min_confidence: float = 0.1  # no pose under this confidence
    rotations: int = 4  # 1: the crop as it is; 4: also turned by 90, 180 and 270 degrees
    turn_margin: float = 1.5  # a turned candidate must beat the upright one by this factor
    turn_below: float = 0.5  # with rotations 4: the turned crops run only where the upright crops' best pose has a
    # confidence under this (or none); 1.01: always
    turns_on_search_model: bool = True  # the turned crops run on the searches' network (`search_model`)
    hypotheses: int = 64  # RANSAC voting hypotheses per keypoint
    cos_threshold: float = 0.99  # a pixel votes for a hypothesis within this cosine
    ransac_px: float = 8.0  # PnP's RANSAC reprojection threshold
    seed: int = 0
    refine: bool = True  # refine the pose on the object's outline
    min_outline_fit: float = 0.7  # with refine: no pose when less of its outline lies on edges
    device: str = "auto"  # "cpu" to keep off CUDA
    search_model: str = "auto"  # the network of the whole-frame searches: "auto", the model's int8 copy
    # `<model>_int8.onnx` beside it where there is one (`flextrack train pvnet-quantize`), else the model; "same":
    # the model; or a path. The crop pass voted on always runs the model itself (docs/pvnet.md, Speed)
    threads: int = 1  # onnxruntime intra-op threads per call (0: its default, every core); the service runs
    # calls on several worker threads at once, and one core a call gives the most frames per core
    keypoint_floor_px: float = KEYPOINT_FLOOR_PX
    keypoint_inflation: float = KEYPOINT_INFLATION
    refine_floor_px: float = REFINE_FLOOR_PX
    refine_inflation: float = REFINE_INFLATION
    refine_edge_power: float = REFINE_EDGE_POWER


def _model_scale(meta: dict, key: str, name: str, model_path: Path) -> int:
    """INPUT_SCALE / OUTPUT_STRIDE as the training side wrote them into the model (export_onnx)."""
    try:
        return int(meta[key])
    except (KeyError, ValueError):
        raise ValueError(f"estimator '{name}': {model_path.name} has no integer '{key}' in its metadata "
                         f"(export it with flextrack.training.export_onnx)") from None


def _providers(device: str) -> list[str]:
    import onnxruntime as ort

    available = ort.get_available_providers()
    wanted = ["CPUExecutionProvider"] if device == "cpu" else ["CUDAExecutionProvider", "CPUExecutionProvider"]
    return [p for p in wanted if p in available]


def _session(path: Path, o: PvnetOptions):
    import onnxruntime as ort

    options = ort.SessionOptions()
    # Every graph optimisation (constant folding, Conv+BatchNorm+Relu fusion, the CPU's blocked NCHWc
    # layout) and one operator at a time: a batch-1 pass of this small network has no parallel branches.
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    # No memory arena and no memory pattern: onnxruntime keeps both per input shape, and frames of several
    # shapes (or crops) made the server hold GBs; without them each run allocates and frees its own.
    options.enable_cpu_mem_arena = False
    options.enable_mem_pattern = False
    # Idle intra-op threads sleep instead of spinning: with several worker threads (and other processes) on
    # the cores, spinning threads burned CPU that the other calls needed.
    options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    if o.threads:
        options.intra_op_num_threads = int(o.threads)
    return ort.InferenceSession(str(path), options, providers=_providers(o.device))


def _search_model(model_path: Path, search_model: str, name: str) -> Path:
    """The whole-frame searches' ONNX file (PvnetOptions.search_model)."""
    if search_model == "same":
        return model_path
    if search_model == "auto":
        int8 = model_path.with_name(f"{model_path.stem}_int8.onnx")
        return int8 if int8.is_file() else model_path
    path = Path(search_model)
    if not path.is_file():
        raise FileNotFoundError(f"estimator '{name}': search_model {path} not found (\"auto\", \"same\" or an ONNX file)")
    return path


def _factor(h: int, w: int, least: int, max_px: int) -> int:
    """The smallest integer reduction, at least `least`, that brings an h x w frame within max_px pixels."""
    return max(least, math.ceil(math.sqrt(h * w / max_px)))


def _window(shape: tuple[int, int], box: tuple, factor: int, side: int) -> tuple[int, int, int, int]:
    """(x, y, width, height) of a side x side window (or the image's size, where smaller) of an image reduced by
    `factor`, centred on a box given in frame pixels and moved inside the image."""
    h, w = shape
    ww, wh = min(side, w), min(side, h)
    cx, cy = (box[0] + box[2]) / 2 / factor, (box[1] + box[3]) / 2 / factor
    x = int(min(max(round(cx - ww / 2), 0), w - ww))
    y = int(min(max(round(cy - wh / 2), 0), h - wh))
    return x, y, ww, wh


def _components(mask: np.ndarray, count: int, min_px: int) -> list[np.ndarray]:
    """The `count` largest 8-connected components of a boolean mask with at least min_px pixels."""
    _, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA]
    order = np.argsort(-areas)[:count]
    return [labels == 1 + int(k) for k in order if areas[k] >= min_px]


def _unturn(points: np.ndarray, vectors: np.ndarray, turns: int, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 2) and vectors (N, K, 2) found in np.rot90(crop, turns) of a size x size crop, in the
    crop's own coordinates. One turn (counter-clockwise) took crop pixel (x, y) to (y, size - 1 - x)."""
    for _ in range(turns % 4):
        points = np.stack([size - 1 - points[:, 1], points[:, 0]], axis=1)
        vectors = np.stack([-vectors[..., 1], vectors[..., 0]], axis=-1)
    return points, vectors


class _Pick(NamedTuple):
    """`_select`'s winner (None: no candidate), its score, its votes (keypoints, spreads: its covariance is
    made once it has won) and the voting and PnP milliseconds over the candidates."""
    best: EstimateOutput | None = None
    score: float = 0.0
    votes: tuple | None = None
    voting_ms: float = 0.0
    pnp_ms: float = 0.0


class PvnetEstimator(Estimator):
    kind = "pvnet"
    version = "1.0"
    uses_image = True
    description = "PVNet-style network (mask + keypoint vector field, onnxruntime), RANSAC voting, OpenCV PnP"

    def __init__(self, objects: ObjectRegistry, model_path: str | Path, name: str = "pvnet", object_ids=(),
                 options: PvnetOptions | None = None, **params):
        """`options`, with `params` (PvnetOptions' field names, as a config file gives them) over it."""
        unknown = set(params) - {f.name for f in dataclass_fields(PvnetOptions)}
        if unknown:
            raise TypeError(f"estimator '{name}': unknown pvnet option(s) {sorted(unknown)}")
        self.options = o = replace(options or PvnetOptions(), **params)
        ids = list(object_ids) or objects.ids()
        if len(ids) != 1:
            raise ValueError(f"estimator '{name}': a pvnet model serves exactly one object, got {ids}; "
                             f"set `objects = [\"...\"]`")
        super().__init__(name, ids)
        model_path = Path(model_path)
        if not model_path.is_file():
            raise FileNotFoundError(f"estimator '{name}': ONNX model {model_path} not found "
                                    f"(train one with `flextrack train pvnet`)")
        if min(o.search_px, o.full_search_px) < 64 * 64:
            raise ValueError(f"estimator '{name}': search_px and full_search_px must be at least 4096 (64x64)")
        if o.window_px != 0 and o.window_px < 64:
            raise ValueError(f"estimator '{name}': window_px must be 0 (the whole frame) or at least 64, got {o.window_px}")
        self.session = _session(model_path, o)
        self.search_model_path = _search_model(model_path, o.search_model, name)
        self.search_session = self.session if self.search_model_path == model_path else \
            _session(self.search_model_path, o)
        object_kp = objects.get(ids[0]).keypoints
        scales = []  # (input_scale: frame -> network input (area), output_stride: network input -> output grid)
        for path, session in [(model_path, self.session)] + (
                [] if self.search_session is self.session else [(self.search_model_path, self.search_session)]):
            meta = session.get_modelmeta().custom_metadata_map
            scales.append((_model_scale(meta, "input_scale", name, path), _model_scale(meta, "output_stride", name, path)))
            model_kp = np.asarray(json.loads(meta.get("keypoints_O", "[]")), dtype=float)
            if model_kp.shape != object_kp.shape or not np.allclose(model_kp, object_kp, atol=1e-4):
                raise ValueError(f"estimator '{name}': {path.name} was trained for other keypoints than object "
                                 f"'{ids[0]}' has ({model_kp.shape[0]} vs {object_kp.shape[0]}, or different positions)")
        if scales[-1] != scales[0]:
            raise ValueError(f"estimator '{name}': {self.search_model_path.name} has another input scale or output "
                             f"stride than {model_path.name}")
        self.input_scale, self.output_stride = scales[0]
        self.model_path = model_path
        self.num_keypoints = len(object_kp)
        self.min_mask_px = int(o.min_mask_px)
        self.zoom, self.zoom_size, self.zoom_object_px = bool(o.zoom), int(o.zoom_size), float(o.zoom_object_px)
        self.full_resolution_search, self.near_box_px = bool(o.full_resolution_search), float(o.near_box_px)
        self.search_px, self.full_search_px = int(o.search_px), int(o.full_search_px)
        self.window_px = int(o.window_px)
        self.candidates, self.candidate_share = int(o.candidates), float(o.candidate_share)
        self.min_confidence = float(o.min_confidence)
        if o.rotations not in (1, 4):
            raise ValueError(f"estimator '{name}': rotations must be 1 (the crop as it is) or 4 (also turned by 90, "
                             f"180 and 270 degrees), got {o.rotations}")
        self.rotations, self.turn_margin, self.turn_below = int(o.rotations), float(o.turn_margin), float(o.turn_below)
        self.turns_on_search_model = bool(o.turns_on_search_model)
        if self.turn_margin < 1:
            raise ValueError(f"estimator '{name}': turn_margin must be >= 1, got {o.turn_margin}")
        self.voting = VotingConfig(hypotheses=int(o.hypotheses), cos_threshold=float(o.cos_threshold))
        self.seed = int(o.seed)
        self._pnp = PnpEstimator(objects, name=f"{name}.pnp", object_ids=ids, ransac_px=o.ransac_px)
        obj = objects.get(ids[0])
        self.refiner = ContourRefiner(obj.vertices, obj.faces, obj.keypoints) if o.refine else None
        self.min_outline_fit = float(o.min_outline_fit)
        self._keypoints_O = obj.keypoints
        if min(o.keypoint_floor_px, o.keypoint_inflation, o.refine_floor_px, o.refine_inflation) <= 0:
            raise ValueError(f"estimator '{name}': the covariance's floors and inflations must be > 0")
        self.keypoint_floor_px, self.keypoint_inflation = float(o.keypoint_floor_px), float(o.keypoint_inflation)
        self.refine_floor_px, self.refine_inflation = float(o.refine_floor_px), float(o.refine_inflation)
        self.refine_edge_power = float(o.refine_edge_power)

    @classmethod
    def from_spec(cls, spec) -> PvnetEstimator:
        spec.check_params({f.name for f in dataclass_fields(PvnetOptions)})
        if spec.model is None:
            raise ValueError(f"estimator '{spec.name}' (kind pvnet) needs `model = \"path/to/pvnet.onnx\"`")
        return cls(spec.objects, spec.model, spec.name, spec.object_ids, **spec.params)

    @property
    def providers(self) -> list[str]:
        return self.session.get_providers()

    # ---- network passes ------------------------------------------------------------------------

    def _run(self, images: list[np.ndarray], search: bool = False) -> np.ndarray:
        """The network's output for images of one size; `search`: on the whole-frame searches' network."""
        x = np.stack(images).astype(np.float32).transpose(0, 3, 1, 2) / np.float32(255.0)
        session = self.search_session if search else self.session
        return session.run(None, {"image": np.ascontiguousarray(x)})[0]

    def _zoom_crop(self, image: np.ndarray, reduced: np.ndarray, factor: int, box: tuple[float, float, float, float]):
        """A square crop around the box, scaled so the object is about zoom_object_px wide: from the frame, or
        from its copy reduced by `factor` (area averaging) where that has enough pixels (less aliasing).

        Returns the crop and (scale, offset) such that frame point u = crop point / scale + offset.
        """
        x0, y0, x1, y1 = box
        side = max(x1 - x0, y1 - y0, 8.0)
        scale = self.zoom_object_px / side  # crop px per frame px
        source, src_scale, src_shift = (image, 1.0, 0.0) if scale * factor > 1.5 else \
            (reduced, 1.0 / factor, (1.0 / factor - 1.0) / 2)
        s = scale / src_scale  # crop px per source px (source u_s = src_scale * u + src_shift)
        c_src = src_scale * np.array([(x0 + x1) / 2, (y0 + y1) / 2]) + src_shift
        M = np.array([[s, 0.0, (self.zoom_size - 1) / 2 - s * c_src[0]],
                      [0.0, s, (self.zoom_size - 1) / 2 - s * c_src[1]]])
        crop = cv2.warpAffine(source, M, (self.zoom_size, self.zoom_size), flags=cv2.INTER_LINEAR,
                              borderMode=cv2.BORDER_REPLICATE)
        # crop c = s * u_s + M[:, 2] = s * (src_scale * u + src_shift) + M[:, 2]  ->  u = (c - off_c) / scale
        off_c = s * src_shift + M[:, 2]
        return crop, scale, off_c

    @staticmethod
    def _field(out: np.ndarray, mask: np.ndarray):
        """Object pixels (rows, cols) and their (N, K, 2) vectors from one network output."""
        rows, cols = np.nonzero(mask)
        vec = out[1:, rows, cols].T.reshape(len(rows), -1, 2)
        return rows, cols, vec

    # ---- estimation ----------------------------------------------------------------------------

    def _check(self, inp: EstimateInput) -> np.ndarray:
        if inp.camera is None:
            raise InvalidInput("pvnet needs the camera intrinsics (fx, fy, cx, cy, width, height)")
        if inp.image is None:
            raise InvalidInput("pvnet needs the frame's image")
        self.resolve_object(inp.object_id)
        image = inp.image if inp.image.ndim == 3 else cv2.cvtColor(inp.image, cv2.COLOR_GRAY2RGB)
        if image.shape[2] != 3 or image.dtype != np.uint8:
            raise InvalidInput(f"pvnet needs an HxWx3 uint8 RGB image, got {image.shape} {image.dtype}")
        if min(image.shape[:2]) < 32:
            raise InvalidInput(f"image of {image.shape[1]}x{image.shape[0]} is too small for pvnet")
        return image

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        return self.estimate_batch([inp])[0]

    def estimate_batch(self, inputs: list[EstimateInput]) -> list[EstimateOutput]:
        """Frames of one size run through the network together; voting and PnP run per frame."""
        images = [self._check(inp) for inp in inputs]
        results: list[EstimateOutput | None] = [None] * len(inputs)
        by_size: dict[tuple, list[int]] = {}
        for i, image in enumerate(images):
            by_size.setdefault(image.shape, []).append(i)
        for idx in by_size.values():
            for i, out in zip(idx, self._estimate_same_size([inputs[i] for i in idx], [images[i] for i in idx])):
                results[i] = out
        return results

    @staticmethod
    def _reduce(images: list[np.ndarray], factor: int) -> list[np.ndarray]:
        if factor == 1:
            return images
        h, w = images[0].shape[:2]
        return [cv2.resize(im, (w // factor, h // factor), interpolation=cv2.INTER_AREA) for im in images]

    def _locate(self, outs: np.ndarray, factor: int) -> list[list]:
        """Per output, the candidate objects, largest first: (pixels (N, 2) and box in frame px, vectors (N, K, 2))."""
        stride = factor * self.output_stride  # frame px per output cell
        shift = (stride - 1) / 2  # centre of an output cell, frame px
        found = []
        for out in outs:
            candidates = []
            for mask in _components(out[0] > 0, self.candidates, self.min_mask_px):
                rows, cols, vec = self._field(out, mask)
                box = (stride * cols.min(), stride * rows.min(), stride * (cols.max() + 1), stride * (rows.max() + 1))
                pixels = np.stack([stride * cols + shift, stride * rows + shift], axis=1).astype(float)
                candidates.append((pixels, vec, box))
            found.append(candidates)
        return found

    def _estimate_same_size(self, inputs, images) -> list[EstimateOutput]:
        n = len(images)
        h, w = images[0].shape[:2]
        t0 = time.perf_counter()
        # Whole-frame search: the halved frame finds near objects; where its largest candidate is
        # missing or small (box side under `near_box_px` of the halved frame) the full-resolution
        # frame is searched too, where far objects have the sizes the network mostly saw. A frame
        # larger than 640x480 is reduced further for both (search_px, full_search_px).
        factor = _factor(h, w, self.input_scale, self.search_px)
        halves = self._reduce(images, factor)
        found = self._locate(self._run(halves, search=True), factor)
        side = lambda box: max(box[2] - box[0], box[3] - box[1])
        small = [i for i, f in enumerate(found) if not f or side(f[0][2]) < self.near_box_px * self.input_scale]
        if self.full_resolution_search and small:
            full = _factor(h, w, 1, self.full_search_px)
            reduced = self._reduce([images[i] for i in small], full)
            near = [k for k, i in enumerate(small) if found[i] and self.window_px]
            whole = [k for k in range(len(small)) if k not in near]
            if whole:  # nothing found (or window_px 0): the whole frame
                for k, f in zip(whole, self._locate(self._run([reduced[k] for k in whole], search=True), full)):
                    found[small[k]] = f or found[small[k]]
            if near:  # a small candidate: a window around it is enough, at a fifth of the cost
                windows = [_window(reduced[k].shape[:2], found[small[k]][0][2], full, self.window_px) for k in near]
                outs = self._run([reduced[k][y:y + wh, x:x + ww] for k, (x, y, ww, wh) in zip(near, windows)],
                                 search=True)
                for k, (x, y, _, _), f in zip(near, windows, self._locate(outs, full)):
                    shift = np.array([x, y], dtype=float) * full
                    f = [(px + shift, vec, (b[0] + shift[0], b[1] + shift[1], b[2] + shift[0], b[3] + shift[1]))
                         for px, vec, b in f]
                    found[small[k]] = f or found[small[k]]
        # A candidate far smaller than the largest is a blob of false mask (a table leg), and its few
        # consistent votes can give a confident-looking pose: only those near the largest's size go on.
        found = [[c for c in f if len(c[0]) >= self.candidate_share * len(f[0][0])] for f in found]
        if not (self.zoom and any(found)):  # per frame, the fields voted on, with the turn they were seen in
            fields = [[(c[0], c[1], 0) for c in f] for f in found]
            inference_ms = (time.perf_counter() - t0) * 1e3 / n
            return [self._solve(inp, self._select(inp, cands), inference_ms) for inp, cands in zip(inputs, fields)]
        # The crop pass, upright; turned (rotations 4) only for frames whose upright crops gave no confident pose:
        # a device held about upright, the common case, costs one crop a candidate instead of four.
        fields = self._crop_fields(images, halves, factor, found, (0,), fallback=True)
        t1 = time.perf_counter()
        picks = [self._select(inp, cands) for inp, cands in zip(inputs, fields)]
        selecting = time.perf_counter() - t1
        upright = list(picks)
        if self.rotations == 4:
            redo = [i for i, pick in enumerate(picks) if found[i] and (
                pick.best is None or pick.best.status != Status.OK or pick.best.confidence < self.turn_below)]
            if redo:
                turned = self._crop_fields([images[i] for i in redo], [halves[i] for i in redo], factor,
                                           [found[i] for i in redo], (1, 2, 3), fallback=False,
                                           search=self.turns_on_search_model)
                t1 = time.perf_counter()
                for i, more in zip(redo, turned):
                    if more:  # the upright crops' pick goes on over the turned ones
                        picks[i] = self._select(inputs[i], more, picks[i])
                selecting += time.perf_counter() - t1
        inference_ms = (time.perf_counter() - t0 - selecting) * 1e3 / n
        return [self._solve_or_upright(inp, pick, first, inference_ms) for inp, pick, first in zip(inputs, picks, upright)]

    def _solve_or_upright(self, inp: EstimateInput, pick: _Pick, upright: _Pick, inference_ms: float) -> EstimateOutput:
        """`_solve`, and where a turned crop's pose won but its outline does not fit the image, the upright crops'
        best solved instead: a network shown a turned object can see a confident wrong one."""
        out = self._solve(inp, pick, inference_ms)
        if out.status == Status.OK or pick.best is upright.best or upright.best is None \
                or upright.best.status != Status.OK:
            return out
        again = self._solve(inp, upright, inference_ms)
        again.stage_ms["refine"] = again.stage_ms.get("refine", 0.0) + out.stage_ms.get("refine", 0.0)
        return again

    def _crop_fields(self, images: list, halves: list, factor: int, found: list[list], turns: tuple[int, ...],
                     fallback: bool, search: bool = False) -> list[list]:
        """Per frame, the fields of the crop pass: one per candidate and turn of its crop, mapped back to
        frame pixels, with the turn; with `fallback`, a candidate whose crop shows no mask in these turns
        keeps its whole-frame field."""
        pairs = [(i, j) for i in range(len(found)) for j in range(len(found[i]))]
        crops = [self._zoom_crop(images[i], halves[i], factor, found[i][j][2]) for i, j in pairs]
        turns = [(p, t) for p in range(len(pairs)) for t in turns]
        zoomed: list[list] = [[] for _ in pairs]
        for (p, t), out in zip(turns, self._run([np.rot90(crops[p][0], t) for p, t in turns], search=search)):
            masks = _components(out[0] > 0, 1, self.min_mask_px)
            if masks:
                rows, cols, vec = self._field(out, masks[0])
                pts, vec = _unturn(np.stack([self.output_stride * cols + 0.5, self.output_stride * rows + 0.5], axis=1),
                                   vec, t, self.zoom_size)
                _, scale, off = crops[p]
                zoomed[p].append(((pts - off) / scale, vec, t))
        fields: list[list] = [[] for _ in found]
        for p, (i, j) in enumerate(pairs):
            fields[i] += zoomed[p] or ([(found[i][j][0], found[i][j][1], 0)] if fallback else [])
        return fields

    def _select(self, inp: EstimateInput, candidates: list, start: _Pick | None = None) -> _Pick:
        """Votes and solves each candidate; the most confident pose wins, a turned crop's only by a factor
        `turn_margin`: the network was trained on objects turned at most about 70 deg from upright, and
        in a crop turned further it may still see an upright one, a pose some pixels off with a
        confidence near the right one's. Turns are for views rolled far from upright, where the
        unturned crop fails. `start`: the pick over earlier candidates to go on from (each candidate's
        votes are seeded alike wherever it comes in the list)."""
        best, best_score, votes, voting_ms, pnp_ms = start or _Pick()
        for pixels, vectors, turn in candidates:
            t1 = time.perf_counter()
            rng = np.random.default_rng([self.seed, inp.frame_id & 0xFFFFFFFF])
            keypoints, inlier_ratio, spreads = vote_with_spread(pixels, vectors, rng, self.voting)
            t2 = time.perf_counter()
            kp_rows = np.column_stack([np.arange(len(keypoints)), keypoints])
            out = self._pnp.estimate(replace(inp, keypoints=kp_rows, image=None))
            if out.status == Status.OK:
                out.confidence = float(out.confidence * np.mean(inlier_ratio))
                out.covariance = None  # the winner's, once it is known (`_solve`)
            voting_ms += (t2 - t1) * 1e3
            pnp_ms += (time.perf_counter() - t2) * 1e3
            score = out.confidence / (self.turn_margin if turn else 1.0)
            if best is None or (out.status == Status.OK and (best.status != Status.OK or score > best_score)):
                best, best_score, votes = out, score, (keypoints, spreads)
        return _Pick(best, best_score, votes, voting_ms, pnp_ms)

    def _solve(self, inp: EstimateInput, pick: _Pick, inference_ms: float) -> EstimateOutput:
        """The selected pose (`_select`), held to min_confidence, refined, with its covariance: the refinement's
        where it moved the pose, else the voted keypoints' through PnP."""
        best = pick.best or EstimateOutput(Status.OBJECT_NOT_FOUND, message="the object mask is too small or empty")
        if best.status == Status.OK and best.confidence < self.min_confidence:
            best = EstimateOutput(Status.OBJECT_NOT_FOUND, message=f"no confident pose (best {best.confidence:.2f} < "
                                  f"min_confidence {self.min_confidence:g})")
        stage_ms = {"inference": inference_ms, "voting": pick.voting_ms, "pnp": pick.pnp_ms}
        if best.status == Status.OK:
            T_pnp = best.T_CO
            if self.refiner is not None and not any(inp.camera.distortion):
                best = self._refine(inp, best, stage_ms)
            if best.status == Status.OK and best.covariance is None:  # PnP's pose, as it was
                t0 = time.perf_counter()
                best.covariance = self._keypoint_covariance(inp, *pick.votes, T_pnp)
                stage_ms["pnp"] += (time.perf_counter() - t0) * 1e3
        best.stage_ms = stage_ms
        return best

    def _refine(self, inp: EstimateInput, out: EstimateOutput, stage_ms: dict) -> EstimateOutput:
        """The pose refined on the image's edges; no pose where the object's outline, drawn at it, does not
        fit the image: a wrong pose (a flipped object, another blob) leaves most of the outline off any
        edge, which the keypoints' confidence does not see."""
        t0 = time.perf_counter()
        image = inp.image if inp.image.ndim == 3 else cv2.cvtColor(inp.image, cv2.COLOR_GRAY2RGB)
        out.T_CO, info = self.refiner.refine(image, inp.camera.K, out.T_CO)
        if not info["kept"] and info["gn"] is not None:
            out.covariance = self._refine_covariance(info["gn"])
        stage_ms["refine"] = (time.perf_counter() - t0) * 1e3
        if info["fit"] < self.min_outline_fit:
            return EstimateOutput(Status.OBJECT_NOT_FOUND, message=f"the outline at the best pose does not fit the "
                                  f"image ({info['fit']:.2f} of it on an edge < min_outline_fit {self.min_outline_fit:g})")
        return out

    # ---- covariance ----------------------------------------------------------------------------

    def keypoint_information(self, inp: EstimateInput, keypoints: np.ndarray, spreads: np.ndarray,
                             T_CO: np.ndarray) -> np.ndarray:
        """sum_i J_i^T (C_i + floor^2 I)^-1 J_i over the keypoints PnP kept (reprojected within its
        RANSAC threshold): J_i the 2x6 Jacobian of keypoint i's projection (wire convention), C_i the
        spread of its votes."""
        K = inp.camera.K
        dist = np.asarray(inp.camera.distortion, dtype=float) if any(inp.camera.distortion) else None
        points = self._keypoints_O
        J = pose_jacobian(T_CO[:3, :3], T_CO[:3, 3], points, K, dist).reshape(-1, 2, 6)
        rvec, _ = cv2.Rodrigues(T_CO[:3, :3])
        projected = cv2.projectPoints(points, rvec, T_CO[:3, 3], K, dist)[0].reshape(-1, 2)
        keep = np.linalg.norm(projected - keypoints, axis=1) < self._pnp.ransac_px
        W = np.linalg.inv(spreads[keep] + self.keypoint_floor_px ** 2 * np.eye(2))
        return np.einsum("nia,nij,njb->ab", J[keep], W, J[keep])

    def _keypoint_covariance(self, inp, keypoints, spreads, T_CO) -> np.ndarray:
        return covariance(self.keypoint_information(inp, keypoints, spreads, T_CO), self.keypoint_inflation)

    def refine_information(self, gn: dict) -> np.ndarray:
        """The refinement's Gauss-Newton information at its solution, J^T J / (s^2 (s / s_ref)^p): J over
        its contour and keypoint-prior rows, s the contour rows' RMS residual (at least refine_floor_px),
        p = refine_edge_power (docs/estimators.md: the pose error grows faster with s than s^2)."""
        J, r, m = gn["J"], gn["r"], gn["m"]
        s = max(float(np.sqrt(np.sum(r[:m] ** 2) / max(m - 6, 1))), self.refine_floor_px)
        return J.T @ J / (s ** 2 * (s / REFINE_EDGE_REF_PX) ** self.refine_edge_power)

    def _refine_covariance(self, gn: dict) -> np.ndarray:
        return covariance(self.refine_information(gn), self.refine_inflation)
