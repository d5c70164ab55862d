"""What both tracker cores share around their refinement: the request book, the initialising frames,
lost requests and the outcome counts. The paper's PRM (`client_sdk.tracker.Tracker`) and the filter
(`client_sdk.eskf.tracker.FilterTracker`) differ only in how a backend answer changes the state."""

from __future__ import annotations

import operator
from dataclasses import dataclass
from math import isfinite

import numpy as np

from client_sdk import initialization
from client_sdk.inspection import Status
from client_sdk.options import TrackerOptions
from client_sdk.refinement import RefinementRequest, RequestBook, ResponseOutcome


@dataclass(frozen=True)
class FrameResult:
    """What `add_frame` returns for one camera frame: its pose, how far to trust it, and whether the
    shell must send this frame to the backend."""

    t_ns: int
    T_CO: np.ndarray | None  # the propagated pose (None only while INITIALIZING); trust it when FINE
    status: Status
    request: RefinementRequest | None  # when set, the shell sends this frame to the backend
    covariance: np.ndarray | None = None  # 6x6 of T_CO (flextrack.wire convention); the filter sets it


def as_int(value, name: str, what: str = "an integer number of nanoseconds") -> int:
    # ValueError for every bad input (not TypeError), as the API promises the shells
    if isinstance(value, bool):
        raise ValueError(f"{name} must be {what}, got {value!r}")  # noqa: TRY004
    try:
        return operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be {what}, got {value!r}") from None


def imu_sample(t_ns, gyro, accel, last_t_ns: int | None) -> tuple:
    """The sample `(t_ns, w 3, a 3)` as floats; ValueError for non-finite values or a time not after the last."""
    t = as_int(t_ns, "t_ns")
    try:  # numpy rows (what the runners pass) become floats in one call, not one scalar at a time
        gx, gy, gz = map(float, gyro.tolist() if isinstance(gyro, np.ndarray) else gyro)
        ax, ay, az = map(float, accel.tolist() if isinstance(accel, np.ndarray) else accel)
    except (TypeError, ValueError):
        raise ValueError("gyro and accel must each be 3 numbers") from None
    if not isfinite(gx + gy + gz + ax + ay + az):
        raise ValueError(f"IMU sample at {t} ns is not finite: gyro {gyro!r}, accel {accel!r}")
    if last_t_ns is not None and t <= last_t_ns:
        raise ValueError(f"IMU sample at {t} ns is not after the previous one at {last_t_ns} ns")
    return (t, gx, gy, gz, ax, ay, az)


def check_rigid(T, name: str) -> list[float]:
    """The 16 entries (row-major) of a rigid 4x4 transform; ValueError otherwise. Plain-float checks:
    this runs on every backend response, where numpy's allclose/det would cost tens of microseconds."""
    T = np.asarray(T, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"{name} must be a 4x4 matrix, got shape {T.shape}")
    m = T.ravel().tolist()
    if not isfinite(sum(m)):
        raise ValueError(f"{name} must be finite")
    r0, r1, r2 = m[0:3], m[4:7], m[8:11]
    dots = [sum(a * b for a, b in zip(u, v)) for u, v in ((r0, r0), (r1, r1), (r2, r2), (r0, r1), (r0, r2), (r1, r2))]
    det = (r0[1] * r1[2] - r0[2] * r1[1]) * r2[0] + (r0[2] * r1[0] - r0[0] * r1[2]) * r2[1] + \
        (r0[0] * r1[1] - r0[1] * r1[0]) * r2[2]
    if max(abs(d - 1.0) for d in dots[:3]) > 1e-4 or max(abs(d) for d in dots[3:]) > 1e-4 or det < 0 or \
            m[12:16] != [0.0, 0.0, 0.0, 1.0]:
        raise ValueError(f"{name} must be a rigid transform (orthonormal rotation, last row 0 0 0 1)")
    return m


class TrackerBase:
    _assess_options: TrackerOptions  # the options the initialisation window is judged by

    def __init__(self) -> None:
        self._book = RequestBook()
        self._init_est: initialization.InitEstimate | None = None
        self.status = Status.INITIALIZING
        self.status_detail = "initializing: waiting for IMU samples"
        self.outcomes = {k: 0 for k in ResponseOutcome}  # responses seen, by outcome

    @property
    def in_flight(self) -> RefinementRequest | None:
        return self._book.in_flight

    def _initializing_frame(self, t: int):
        request = None
        if self._book.in_flight is None:
            est, detail = initialization.assess(self._buf, t, self._assess_options)
            if est is not None:
                self._init_est = est
                request = self._book.issue(t, "init")
        else:
            detail = f"initializing: waiting for the first backend pose (request {self._book.in_flight.request_id})"
        self.status, self.status_detail = Status.INITIALIZING, detail
        return FrameResult(t, None, Status.INITIALIZING, request)

    def on_backend_failure(self, request_id: int) -> bool:
        """The shell lost this request (timeout, broken stream): the next frame asks again.
        True when it was the live request, False when it was already stale."""
        if not self._book.is_live(as_int(request_id, "request_id", "an integer")):
            return False
        self._book.in_flight = None
        return True

    def _answered(self, request_id: int, capture_t_ns: int) -> int | None:
        """The capture time of the live request this answer is for; None (counted STALE) for any other.
        ValueError when the answer's capture time is not its request's."""
        rid = as_int(request_id, "request_id", "an integer")
        t0 = as_int(capture_t_ns, "capture_t_ns")
        if not self._book.is_live(rid):
            self._outcome(ResponseOutcome.STALE, None)
            return None
        req = self._book.in_flight
        if t0 != req.frame_t_ns:
            raise ValueError(f"response {rid} is for capture time {t0} ns, but the request was for {req.frame_t_ns} ns")
        return t0

    def _outcome(self, outcome: ResponseOutcome, detail: str | None) -> ResponseOutcome:
        self.outcomes[outcome] += 1
        if detail is not None:
            self.status_detail = detail
        return outcome

