"""What a tracking run produced, frame by frame, and its per-sequence errors.

`TrackRecord` collects, for every frame, the tracker's T_CO estimate (with its covariance when the
tracker keeps one), the ground truth and the status; `summarize` turns it into the paper's
per-sequence means (position mm, orientation deg, 2D projection px on the object's model vertices,
as in Table 2), the jitter (RMS of the frame-to-frame change of the 2D error vector), the NEES of
the pose against the truth, and the worst frame called FINE; `write` saves the per-frame CSV, the
summary and TUM trajectories (estimate and ground truth) that `evo` reads.

The errors are measured on at most `METRIC_POINTS` of the model's vertices (every k-th, in file
order): projecting all 12k vertices of a model for each of 3600 frames would cost more than the
tracking itself, and the mean over an even subset differs from the full mean by far less than the
errors we report.
"""

from __future__ import annotations

import csv
import json
import math
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass, field
from itertools import islice
from pathlib import Path

import numpy as np

from flextrack import wire
from flextrack.evaluation.consistency import model_nees_interval, nees_mean_interval
from flextrack.formats import tum
from flextrack.geometry import metrics
from flextrack.geometry.camera import PinholeCamera

METRIC_POINTS = 1000
SCORE_CHUNK = 64  # frames projected at once: their temporaries (~5 MB) are what a live run's RSS swings by


def metric_points(vertices_O: np.ndarray, max_points: int = METRIC_POINTS) -> np.ndarray:
    """Every k-th vertex, k chosen so that at most `max_points` remain."""
    step = max(1, -(-len(vertices_O) // max_points))
    return np.asarray(vertices_O, dtype=float)[::step]


@dataclass
class FrameRow:
    frame_id: int
    t_ns: int
    status: str
    T_CO: np.ndarray | None  # the tracker's estimate; None while it has none
    T_gt: np.ndarray | None
    covariance: np.ndarray | None = None  # 6x6 of T_CO (flextrack.wire convention), when the tracker gave one
    proj_px: float = math.nan
    pos_mm: float = math.nan
    ori_deg: float = math.nan
    jitter_px: float = math.nan  # against the previous frame, when both are scored
    nees: float = math.nan  # e^T covariance^-1 e of the pose error e (wire convention)
    nees_rotation: float = math.nan  # the same of its rotation part alone (3 for a consistent tracker)
    index: int = 0  # position in the record


_SCORES = ("proj_px", "pos_mm", "ori_deg", "jitter_px", "nees", "nees_rotation")
_POSES = (("T_CO", (4, 4)), ("T_gt", (4, 4)), ("covariance", (6, 6)))  # NaN where the row has none
ROW_DTYPE = np.dtype([("frame_id", "i8"), ("t_ns", "i8"), ("index", "i8"), ("status", "U32")]
                     + [(name, "f8", shape) for name, shape in _POSES] + [(name, "f8") for name in _SCORES])


def _rows_to_array(rows: list[FrameRow]) -> np.ndarray:
    out = np.zeros(len(rows), ROW_DTYPE)
    for k, row in enumerate(rows):
        out[k]["frame_id"], out[k]["t_ns"], out[k]["index"], out[k]["status"] = \
            row.frame_id, row.t_ns, row.index, row.status
        for name, _ in _POSES:
            value = getattr(row, name)
            out[k][name] = np.nan if value is None else value
        for name in _SCORES:
            out[k][name] = getattr(row, name)
    return out


def _array_to_rows(rows: np.ndarray) -> list[FrameRow]:
    def pose(value: np.ndarray) -> np.ndarray | None:
        return None if np.isnan(value).all() else value.copy()

    return [FrameRow(int(r["frame_id"]), int(r["t_ns"]), str(r["status"]), pose(r["T_CO"]), pose(r["T_gt"]),
                     pose(r["covariance"]), *(float(r[name]) for name in _SCORES), index=int(r["index"]))
            for r in rows]


class RowStore(Sequence):
    """A record's rows: all in memory, or with `keep` set, at most the last 2 x `keep` in memory and the older
    ones, `keep` at a time, in an anonymous temporary file as numpy records (ROW_DTYPE, no Python objects).
    Why: a live run lasts as long as the device runs, and one row a frame held in memory grows the process
    without end (~1 kB a frame, 3.5 MiB a minute at 60 FPS); on disk the run's memory levels off, and the whole
    record is read back, a chunk at a time, only when it is scored or written at the end."""

    def __init__(self, keep: int | None = None):
        if keep is not None and keep < 1:
            raise ValueError(f"keep must be >= 1 rows, got {keep}")
        self.keep = keep
        self._recent: list[FrameRow] = []
        self._spilled = 0  # rows on disk
        self._file = None

    def append(self, row: FrameRow) -> None:
        self._recent.append(row)

    def full(self) -> bool:
        """Whether the rows in memory should go to disk (the caller scores them first: rows on disk are final)."""
        return self.keep is not None and len(self._recent) >= 2 * self.keep

    def spill(self) -> None:
        """Move all but the last `keep` rows in memory to the file."""
        out, self._recent = self._recent[:-self.keep], self._recent[-self.keep:]
        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="flextrack-rows-")  # noqa: SIM115 - closed with the record
        self._file.seek(0, 2)
        np.save(self._file, _rows_to_array(out), allow_pickle=False)
        self._spilled += len(out)

    def recent(self) -> list[FrameRow]:
        """The rows still in memory (the last ones)."""
        return self._recent

    def __len__(self) -> int:
        return self._spilled + len(self._recent)

    def __iter__(self) -> Iterator[FrameRow]:
        position, read = 0, 0
        while read < self._spilled:
            self._file.seek(position)
            chunk = np.load(self._file, allow_pickle=False)
            position = self._file.tell()
            read += len(chunk)
            yield from _array_to_rows(chunk)
        yield from list(self._recent)

    def __getitem__(self, index):
        if isinstance(index, slice):
            return list(self)[index]
        i = index + len(self) if index < 0 else index
        if not 0 <= i < len(self):
            raise IndexError("row index out of range")
        if i >= self._spilled:
            return self._recent[i - self._spilled]
        return next(islice(iter(self), i, None))


@dataclass
class Summary:
    frames: int
    scored_frames: int  # frames with both an estimate and a ground truth
    pos_mm: float
    ori_deg: float
    proj_px: float
    proj_px_p95: float
    proj_px_max: float
    jitter_px: float = math.nan  # RMS over frames and model points
    nees_mean: float = math.nan  # over scored frames with a covariance (6 for a consistent tracker)
    nees_frames: int = 0
    nees_rotation_mean: float = math.nan  # the rotation block's alone (3): where a NEES off 6 comes from
    nees_lo: float = math.nan  # the 95 % interval of nees_mean for a consistent tracker, allowing for
    nees_hi: float = math.nan  # correlated frames (flextrack.evaluation.consistency)
    nees_interval_from: str = ""  # "model": the filter's error dynamics; "autocorrelation": the NEES series'
    fine_frames: int = 0
    worst_fine_px: float = math.nan  # the largest 2D error of a frame called FINE
    status_counts: dict[str, int] = field(default_factory=dict)
    requests: int = 0
    median_request_kb: float = math.nan  # the requests' serialized size, median, kB of 1024 bytes
    responses: int = 0
    failures: int = 0
    bad_covariances: int = 0  # answers whose covariance was refused (the tracker's default used)
    time_offset_ms: float = math.nan  # the filter's estimate of the camera-IMU offset at the end (t_imu - t_camera)
    time_offset_sigma_ms: float = math.nan  # its standard deviation, as the filter has it


@dataclass
class TrackRecord:
    camera: PinholeCamera
    vertices_O: np.ndarray  # (N, 3) m, the model's vertices (the 2D error uses `metric_points` of them)
    rows: RowStore = field(default_factory=RowStore)  # RowStore(keep=N): older rows on disk (a live run)
    requests: int = 0
    request_bytes: list[int] = field(default_factory=list)  # each request's serialized size, in the order sent
    responses: int = 0
    failures: int = 0
    first_refusal: str = ""  # the first answer that was not OK: "STATUS: the server's message"
    bad_covariances: int = 0
    time_offset_ms: float = math.nan
    time_offset_sigma_ms: float = math.nan
    error_dynamics: object | None = None  # the filter's, when it kept them (client_sdk.eskf.error_dynamics)

    def __post_init__(self) -> None:
        self._points = metric_points(self.vertices_O)

        self._unscored: list[FrameRow] = []
        self._last_error: tuple[FrameRow, np.ndarray] | None = None  # the last scored frame's 2D error vectors

    def add(self, frame_id: int, t_ns: int, status: str, T_CO: np.ndarray | None, T_gt: np.ndarray | None,
            covariance: np.ndarray | None = None) -> FrameRow:
        """Keep one frame; its errors are computed, in a batch, when first asked for."""
        row = FrameRow(int(frame_id), int(t_ns), status, None if T_CO is None else np.array(T_CO, float),
                       None if T_gt is None else np.asarray(T_gt, float), covariance, index=len(self.rows))
        self.rows.append(row)
        if row.T_CO is not None and row.T_gt is not None:
            self._unscored.append(row)
        if self.rows.full():
            self._score_pending()  # rows on disk are final
            self.rows.spill()
        return row

    def last_scored(self) -> FrameRow | None:
        """The latest frame with its errors filled in, without reading the rows on disk (progress lines)."""
        self._score_pending()
        return next((r for r in reversed(self.rows.recent()) if r.T_CO is not None and r.T_gt is not None), None)

    def scored(self) -> list[FrameRow]:
        """Frames with an estimate and a ground truth, their errors filled in."""
        self._score_pending()
        return [r for r in self.rows if r.T_CO is not None and r.T_gt is not None]

    def _score_pending(self) -> None:
        if self._unscored:
            pending, self._unscored = self._unscored, []
            previous = self._last_error[1] if self._last_error is not None and self._follows(self._last_error[0],
                                                                                             pending[0]) else None
            proj, jitter, last = metrics.proj_and_jitter_many(
                np.stack([r.T_CO for r in pending]), np.stack([r.T_gt for r in pending]), self.camera, self._points,
                chunk=SCORE_CHUNK, previous=previous)
            self._last_error = (pending[-1], last)
            for k, (row, px) in enumerate(zip(pending, proj)):
                row.proj_px = float(px)
                row.pos_mm = metrics.te_mm(row.T_CO, row.T_gt)
                row.ori_deg = metrics.re_deg(row.T_CO, row.T_gt)
                # jitter only between frames that follow each other (a gap: the shake is not defined)
                if k == 0 or self._follows(pending[k - 1], row):
                    row.jitter_px = float(jitter[k])
            self._score_nees([r for r in pending if r.covariance is not None])

    @staticmethod
    def _score_nees(rows: list[FrameRow]) -> None:
        """Each row's NEES and its rotation block's, in one batched solve each."""
        if not rows:
            return
        e = np.stack([wire.pose_error(r.T_CO, r.T_gt) for r in rows])[..., None]  # (F, 6, 1)
        covariances = np.stack([r.covariance for r in rows])
        nees = (e * np.linalg.solve(covariances, e)).sum(axis=(1, 2))
        nees_rotation = (e[:, :3] * np.linalg.solve(covariances[:, :3, :3], e[:, :3])).sum(axis=(1, 2))
        for row, value, value_rotation in zip(rows, nees, nees_rotation):
            row.nees, row.nees_rotation = float(value), float(value_rotation)

    def _follows(self, earlier: FrameRow, row: FrameRow) -> bool:
        return row.index == earlier.index + 1

    def summarize(self) -> Summary:
        scored = self.scored()  # fills in the errors of every frame
        proj = np.array([r.proj_px for r in scored])
        jitter = np.array([r.jitter_px for r in scored if math.isfinite(r.jitter_px)])
        with_nees = [r for r in scored if math.isfinite(r.nees)]
        nees = np.array([r.nees for r in with_nees])
        fine = [r.proj_px for r in scored if r.status == "FINE"]
        counts: dict[str, int] = {}
        for r in self.rows:
            counts[r.status] = counts.get(r.status, 0) + 1

        def mean(values) -> float:
            return float(np.mean(values)) if len(values) else math.nan

        dynamics = self.error_dynamics
        if dynamics is not None and all(r.t_ns in dynamics.frames for r in with_nees):
            interval, source = model_nees_interval([(r.t_ns, r.covariance) for r in with_nees], dynamics), "model"
        else:
            interval, source = nees_mean_interval(nees), "autocorrelation"

        return Summary(
            frames=len(self.rows), scored_frames=len(scored),
            pos_mm=mean([r.pos_mm for r in scored]), ori_deg=mean([r.ori_deg for r in scored]),
            proj_px=mean(proj), proj_px_p95=float(np.percentile(proj, 95)) if len(proj) else math.nan,
            proj_px_max=float(proj.max()) if len(proj) else math.nan,
            jitter_px=float(np.sqrt(np.mean(jitter ** 2))) if len(jitter) else math.nan,
            nees_mean=mean(nees), nees_frames=len(nees),
            nees_rotation_mean=mean([r.nees_rotation for r in with_nees]),
            nees_lo=interval.lo, nees_hi=interval.hi, nees_interval_from=source if len(nees) else "", fine_frames=counts.get("FINE", 0),
            worst_fine_px=max(fine) if fine else math.nan, status_counts=counts,
            requests=self.requests, responses=self.responses, failures=self.failures,
            median_request_kb=float(np.median(self.request_bytes)) / 1024 if self.request_bytes else math.nan,
            bad_covariances=self.bad_covariances, time_offset_ms=self.time_offset_ms,
            time_offset_sigma_ms=self.time_offset_sigma_ms)

    def write(self, out_dir: str | Path, name: str = "track", provenance: dict | None = None) -> Path:
        """frames.csv, summary.json and TUM files (estimate and ground truth) under out_dir; `provenance`
        (flextrack.provenance.provenance(...)) goes into summary.json under that key."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        scored = self.scored()
        with open(out / f"{name}_frames.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["frame_id", "t_ns", "status", "pos_mm", "ori_deg", "proj_px", "jitter_px", "nees"])
            for r in self.rows:
                w.writerow([r.frame_id, r.t_ns, r.status, f"{r.pos_mm:.6f}", f"{r.ori_deg:.6f}", f"{r.proj_px:.6f}",
                            f"{r.jitter_px:.6f}", f"{r.nees:.6f}"])
        if scored:
            t = np.array([r.t_ns for r in scored], dtype=np.int64)
            tum.write_tum(out / f"{name}_estimate.tum", t, np.stack([r.T_CO for r in scored]))
            tum.write_tum(out / f"{name}_groundtruth.tum", t, np.stack([r.T_gt for r in scored]))
        summary = asdict(self.summarize()) | ({"provenance": provenance} if provenance is not None else {})
        (out / f"{name}_summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        return out


def format_table(rows: list[tuple[str, Summary]]) -> str:
    """A small Markdown table of summaries, one line per named run."""
    lines = [("| run | frames | FINE % | pos mm | ori deg | proj px | proj p95 px | jitter px | NEES | worst FINE px "
              "| requests | failures |"),
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name, s in rows:
        fine = 100.0 * s.status_counts.get("FINE", 0) / max(1, s.frames)
        lines.append(f"| {name} | {s.frames} | {fine:.0f} | {s.pos_mm:.2f} | {s.ori_deg:.3f} | {s.proj_px:.3f} | "
                     f"{s.proj_px_p95:.3f} | {s.jitter_px:.3f} | {s.nees_mean:.2f} | {s.worst_fine_px:.2f} | "
                     f"{s.requests} | {s.failures} |")
    return "\n".join(lines)
