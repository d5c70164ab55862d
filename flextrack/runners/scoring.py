"""Which frames of a run are scored, and why the others are not.

A frame is *in view* when the ground truth puts the object's centre in front of the camera and projects it
into the image; the others (and frames without ground truth) are *out of view* and never scored. Of the
frames in view, those before the tracker's first pose are *initialising*; the rest have an estimate, which
the tracker calls FINE or not (TRACKING_LOST, WRONG_POSE: *lost*). `flextrack track` scores every in-view
frame with an estimate; `flextrack experiment euroc` only the FINE ones (the paper's rule). `Accounting`
counts each group, names the worst FINE frame, and says in one line why a run scored nothing. Frames whose
ground truth is known to be wrong (a recording's motion capture jumping where the IMU did not) can be *set
aside*: counted in view, never scored.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np

from flextrack.formats.sequence import Sequence
from flextrack.geometry.camera import PinholeCamera


class NothingScored(RuntimeError):
    """A run that scored no frame; the message says why, in one line."""


def in_view(T_CO: np.ndarray, camera: PinholeCamera) -> bool:
    """The object's origin in front of the camera and projected inside the image."""
    centre = np.asarray(T_CO, float)[:3, 3]
    if centre[2] <= 0:
        return False
    u, v = camera.project(centre[None])[0]
    return bool(0 <= u < camera.width and 0 <= v < camera.height)


def in_view_only(seq: Sequence) -> Sequence:
    """The sequence with ground truth kept only on the frames that have the object in view."""
    return dataclasses.replace(seq, gt_T_CO={k: T for k, T in seq.gt_T_CO.items() if in_view(T, seq.camera)})


@dataclass
class Accounting:
    frames: int
    in_view: int
    out_of_view: int  # no ground truth in view (out of the image, behind the camera, or none recorded)
    initialising: int  # in view, before the tracker's first pose
    estimated: int  # in view with an estimate
    fine: int  # ... that the tracker called FINE
    lost: dict[str, int] = field(default_factory=dict)  # ... that it did not, by status
    scored: int = 0
    scored_rule: str = "in view, with an estimate"
    worst_fine_frame: int | None = None
    worst_fine_px: float = math.nan
    requests: int = 0
    responses: int = 0
    set_aside: int = 0  # in view, but their ground truth doubtful: not scored
    worst_set_aside_px: float = math.nan  # the worst FINE frame among those, for the record

    def describe(self) -> str:
        """Two lines: the counts, and what was not scored and why."""
        lost = sum(self.lost.values())
        lost_detail = f" ({', '.join(f'{k} {v}' for k, v in sorted(self.lost.items()))})" if lost else ""
        worst = (f"; worst FINE frame {self.worst_fine_frame}: {self.worst_fine_px:.2f} px"
                 if self.worst_fine_frame is not None else "")
        not_scored = [f"{self.out_of_view} out of view", f"{self.initialising} initialising"]
        if self.set_aside:
            not_scored.append(f"{self.set_aside} set aside (ground truth doubtful)")
        if self.scored_rule != "in view, with an estimate":
            not_scored.append(f"{lost} lost{lost_detail}")
        return (f"{self.frames} frames: {self.in_view} with the object in view, {self.fine} of them FINE; "
                f"scored {self.scored} ({self.scored_rule}){worst}\n"
                f"not scored: {', '.join(not_scored)}"
                + ("" if self.scored_rule != "in view, with an estimate" or not lost
                   else f"; of those scored, {lost} not FINE{lost_detail}"))

    def nothing_scored_reason(self) -> str | None:
        """One line saying why no frame was scored; None when some were."""
        if self.scored:
            return None
        if not self.in_view:
            return (f"the object is in view in none of the {self.frames} frames (in front of the camera with its "
                    "centre in the image); place it where the camera looks (convert-euroc --object-position / "
                    "--object-distance)")
        if self.initialising == self.in_view:
            if not self.requests:
                why = ("it never asked the backend for a first pose: the device was never still for the 0.5 s "
                       "the paper's initialisation needs (try --tracker filter, which starts while moving)")
            elif not self.responses:
                why = (f"the backend answered none of its {self.requests} requests with a pose (the object was out "
                       "of view at those frames, or the estimator does not know this sequence or object)")
            else:
                why = "its first pose came only after the last frame with the object in view"
            return f"the tracker never initialised while the object was in view: {why}"
        return (f"no frame in view was FINE ({', '.join(f'{k} {v}' for k, v in sorted(self.lost.items()))}): "
                "the tracker lost the object wherever it was in view")


def account(record, fine_only: bool = False, set_aside: frozenset[int] = frozenset()) -> Accounting:
    """Count a TrackRecord's frames (its rows' ground truth already limited to in-view frames, see
    `in_view_only`); `fine_only`: score only the FINE frames; `set_aside`: frame ids whose ground truth is
    doubtful, counted in view but not scored."""
    rows = record.rows
    record.scored()  # fills in the errors
    in_view_rows = [r for r in rows if r.T_gt is not None]
    estimated = [r for r in in_view_rows if r.T_CO is not None]
    fine_all = [r for r in estimated if r.status == "FINE"]
    fine = [r for r in fine_all if r.frame_id not in set_aside]
    aside_fine = [r.proj_px for r in fine_all if r.frame_id in set_aside]
    lost: dict[str, int] = {}
    for r in estimated:
        if r.status != "FINE":
            lost[r.status] = lost.get(r.status, 0) + 1
    worst = max(fine, key=lambda r: r.proj_px) if fine else None
    return Accounting(
        frames=len(rows), in_view=len(in_view_rows), out_of_view=len(rows) - len(in_view_rows),
        initialising=len(in_view_rows) - len(estimated), estimated=len(estimated), fine=len(fine_all), lost=lost,
        scored=len(fine) if fine_only else len(estimated) - sum(r.frame_id in set_aside for r in estimated),
        scored_rule="in view and FINE" if fine_only else "in view, with an estimate",
        worst_fine_frame=None if worst is None else worst.frame_id,
        worst_fine_px=math.nan if worst is None else worst.proj_px,
        requests=record.requests, responses=record.responses,
        set_aside=sum(r.frame_id in set_aside for r in in_view_rows),
        worst_set_aside_px=max(aside_fine) if aside_fine else math.nan)
