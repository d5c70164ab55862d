"""The tracker core with an error-state Kalman filter: the same events and outputs as `client_sdk.Tracker`.

    tracker = FilterTracker(TrackerOptions(), camera, T_BC, bbox_corners_O)
    tracker.add_imu(t_ns, gyro, accel)           # nominal state and covariance, every sample
    result = tracker.add_frame(t_ns)             # pose, its covariance, status; maybe a request
    tracker.on_backend_response(request_id, capture_t_ns, T_CO, ok, covariance)   # update at t0
    tracker.pose_at(t_ns), tracker.pose_covariance_at(t_ns)
    tracker.error_dynamics                       # with FilterOptions.record_error_dynamics: for the NEES interval

What differs from the paper's PRM (docs/tracker.md has the equations):

- Every IMU sample propagates the state and its 19x19 error covariance (`eskf.propagator`).
- A backend answer for capture time t0 updates state and covariance at t0 + td (td, the camera-IMU
  time offset, is a state) with the answer's own covariance, or a documented default when it sent
  none; the buffered IMU is then re-propagated to now. Gravity's direction in O and the biases are
  states: the answers correct them through the covariance, no gains.
- Outliers: an answer failing the chi-square test on its innovation is rejected (GATED);
  `max_rejections` in a row mean the filter is the one that is wrong: it re-initialises from that
  answer and says so.
- Initialisation does not wait for a still device: a moving start takes gravity's direction from
  the IMU window with a wider uncertainty.
- The status: the PIA as before, and a pose whose projected 1-sigma uncertainty exceeds
  `max_sigma_px` is TRACKING_LOST ("uncertain"), so a doubtful pose is never FINE; nor is one whose
  latest answer was gated (the filter's model failed: a real phone's IMU jolts), until one is applied.

No threads, sockets, sleeps or clocks; the same events give the same outputs, bit for bit.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from client_sdk import initialization
from client_sdk import state as state_codec
from client_sdk.eskf import coasting
from client_sdk.eskf.error_dynamics import ErrorDynamics
from client_sdk.eskf.initializer import initial_state
from client_sdk.eskf.noise_matching import NoiseMatcher, blocks
from client_sdk.eskf.pose_update import pose_covariance, pose_jacobian, update
from client_sdk.eskf.propagator import CovariancePropagator
from client_sdk.eskf.state import BG, TD, FilterState, G
from client_sdk.imu_buffer import ImuBuffer
from client_sdk.inspection import PoseInspector, Status
from client_sdk.options import TrackerOptions
from client_sdk.propagation import NS, measured, rotate, step_midpoint
from client_sdk.refinement import ResponseOutcome
from client_sdk.state import TrackerState
from client_sdk.tracker_base import FrameResult, TrackerBase, as_int, check_rigid, imu_sample
from flextrack import wire
from flextrack.geometry import so3
from flextrack.geometry.camera import PinholeCamera

_DEG = np.pi / 180.0
SETTLE_ANSWERS = 20  # answers after a (re-)initialisation before the noise fits take them


def _within_wire(cov: np.ndarray) -> np.ndarray:
    """A pose covariance scaled down, rotation and translation blocks apart, to the wire's largest meaningful
    standard deviations (`wire.MAX_STD_RAD`, `wire.MAX_STD_M`): a pose coasted for seconds across a gap of
    the IMU's stream is that uncertain, and a prior beyond them is refused as nonsense (it says as little)."""
    d = cov.diagonal().tolist()  # floats: this runs on every request's prior
    kr = min(1.0, 0.99 * wire.MAX_STD_RAD / max(max(d[0:3]), 1e-300) ** 0.5)
    kt = min(1.0, 0.99 * wire.MAX_STD_M / max(max(d[3:6]), 1e-300) ** 0.5)
    if kr == 1.0 and kt == 1.0:
        return cov
    k = np.array([kr] * 3 + [kt] * 3)
    return cov * np.outer(k, k)


def _carried(st: FilterState, before: FilterState) -> FilterState:
    """A re-initialisation inside a gap of the IMU's stream keeps the biases and gravity (and their covariance)
    of the state it replaces: no sample measures them there, the object and the device still share them, and
    a stale sample's specific force, turned by the new pose, put gravity tens of degrees off (`nexus5_ar_a`:
    the velocity jumped ~0.8 m/s, 10 cm in 0.1 s, when the samples came back)."""
    P = before.cov
    c = before.c
    if before.held is not None:  # the bias as it was, not the gap's rate
        c = tuple(before.held[0]) + tuple(c[3:])
        P = P.copy()
        P[BG, :] = 0.0
        P[:, BG] = 0.0
        P[BG, BG] = before.held[1]
    cov = st.cov.copy()
    k = slice(BG.start, G.stop)  # b_g, b_a, g_O
    cov[k, :] = 0.0
    cov[:, k] = 0.0
    cov[k, k] = P[k, k]
    return replace(st, c=tuple(c[0:9]), cov=cov)


class FilterTracker(TrackerBase):
    """PPM, PIM and an ESKF refinement around one buffered state. See module doc."""

    def __init__(self, options: TrackerOptions | None, camera: PinholeCamera, T_BC: np.ndarray,
                 bbox_corners_O: np.ndarray) -> None:
        super().__init__()
        self.options = options if options is not None else TrackerOptions()
        o, fo = self.options, self.options.filter
        T_BC = np.array(check_rigid(T_BC, "T_BC")).reshape(4, 4)
        self._R_CB = T_BC[:3, :3].T.copy()
        self._t_CB = -self._R_CB @ T_BC[:3, 3]
        self._R_CB_floats, self._t_CB_floats = tuple(self._R_CB.ravel().tolist()), tuple(self._t_CB.tolist())
        self.camera = camera
        self.inspector = PoseInspector(camera, bbox_corners_O, o.area_divisor, o.px_error, o.px_motion,
                                       o.base_rate, o.near_m)
        self._corners_O = np.asarray(bbox_corners_O, dtype=float)
        self._assess_options = replace(o, init_require_still=False)  # the filter starts while moving
        self._prop = CovariancePropagator(fo)
        self._max_gap_ns = round(fo.max_imu_gap_s * 1e9)
        self._matchers = (NoiseMatcher(fo.noise_match_answers, 1), NoiseMatcher(fo.noise_match_answers, 3)) \
            if fo.match_imu_noise else None
        self._gap_noise = coasting.GapNoise(fo, fo.noise_match_answers)
        self._floor_var = np.array([(fo.answer_floor_rotation_deg * _DEG) ** 2] * 3
                                   + [fo.answer_floor_translation_m ** 2] * 3)
        self._default_sigma = np.diag([(fo.default_rotation_std_deg * _DEG) ** 2] * 3
                                      + [fo.default_translation_std_m ** 2] * 3)
        self._buf = ImuBuffer(round(o.imu_buffer_s * 1e9))
        self._anchor: tuple[int, FilterState] | None = None  # the state set by the last answer, at its time
        self._td = fo.time_offset_s
        self._last_frame_t: int | None = None
        self._last_uv: np.ndarray | None = None
        self._corrected = False
        self._rejected = 0  # answers rejected in a row
        self._since_start = 0  # answers since the last (re-)initialisation
        self._ease = (np.zeros(6), 0)  # (pose offset still to ease in, camera time it was set)
        self._frame_interval_s = 0.0
        self.error_dynamics = ErrorDynamics() if fo.record_error_dynamics else None

    # ------------------------------------------------------------------ properties
    @property
    def initialized(self) -> bool:
        return self._anchor is not None

    @property
    def imu_noise_densities(self) -> tuple[float, float]:
        """The gyro and accelerometer white-noise densities the filter uses now (`adapt_imu_noise`)."""
        return self._prop.densities

    @property
    def time_offset_s(self) -> float:
        """The estimated camera-IMU time offset (t_imu = t_camera + offset)."""
        return self._td

    @property
    def time_offset_std_s(self) -> float:
        """The time offset's standard deviation after the last answer (nan before the first)."""
        return float("nan") if self._anchor is None else float(self._anchor[1].cov[TD, TD]) ** 0.5

    @property
    def now_ns(self) -> int | None:
        last = self._buf.last_t_ns
        if self._anchor is None:
            return last
        return self._anchor[0] if last is None else max(last, self._anchor[0])

    @property
    def state(self) -> TrackerState | None:
        if self._anchor is None:
            return None
        t = self.now_ns
        st = self._nominal_at(t)
        c = st.c if st.held is None else tuple(st.held[0]) + tuple(st.c[3:])  # the gyro bias, not a gap's rate
        return TrackerState.from_tuples(t, st.x, c)

    @property
    def covariance(self) -> np.ndarray | None:
        """The error-state covariance (19x19, `eskf.state` order) at `now_ns`."""
        return None if self._anchor is None else self._full_at(self.now_ns).cov.copy()

    # ------------------------------------------------------------------ PPM
    def add_imu(self, t_ns: int, gyro, accel) -> None:
        """Propagate state and covariance to this IMU sample and keep it (ValueError, no change, if bad)."""
        buf = self._buf
        last = buf.last_t_ns
        s = imu_sample(t_ns, gyro, accel, last)
        t = s[0]
        self._prop.observe(s)
        new = None
        if self._anchor is not None:
            prev = buf.samples[-1] if buf.samples else s
            a_t, a_st = self._anchor
            base_t, base = (a_t, a_st) if last is None or a_t >= last else (last, buf.states[-1])
            new = self._step(base, base_t, t, prev, s)
        buf.append(s, new)

    def _step(self, st: FilterState, t0: int, t1: int, s0: tuple, s1: tuple) -> FilterState:
        gap = self._max_gap_ns  # `propagation.measured`, inline: this runs for every (re-)propagated sample
        if s1[0] - s0[0] <= gap and t1 - s1[0] <= gap:
            if st.held is not None:
                st = self._leave_gap(st, t0)
            x = step_midpoint(st.x, st.c, t0, t1, s0, s1)
            cov = self._prop.step(st.cov, x, st.c, t0, t1, s0, s1)
            phi = st.phi
            if phi is not None and t1 > t0:  # recording the error dynamics
                phi = self._prop.last_transition @ phi
            return FilterState(x, st.c, cov, phi)
        if st.held is None:  # an interval the IMU did not measure: `eskf.coasting`
            fresh = t0 - s0[0] <= gap
            st = coasting.enter(st, t0, s0[1:4] if fresh else None, self._rate_noise_var(t0) if fresh else 0.0,
                                self.options.filter.gap_rate_std)
        dt = (t1 - t0) * NS
        if dt <= 0:
            return st
        q_alpha, q_a = self._gap_noise.densities
        cov, phi_step = coasting.step_cov(st.cov, st.c, dt, q_alpha, q_a, self._prop.walks[1])
        phi = None if st.phi is None else phi_step @ st.phi
        return FilterState(coasting.step_x(st.x, st.c, dt), st.c, cov, phi, st.held)

    def _leave_gap(self, st: FilterState, t: int) -> FilterState:
        st = coasting.leave(st, t, self._prop.walks[0])
        if st.phi is None:
            return st
        phi = st.phi.copy()
        phi[BG, :] = 0.0  # the bias's error from here on is unrelated to the gap's rate error
        return replace(st, phi=phi)

    def _base_at(self, t: int) -> tuple[int, int, FilterState] | None:
        """(buffer index at or before t, base time, base state): the anchor or the stored state before t."""
        buf = self._buf
        i = buf.index_at_or_before(t)
        a = self._anchor
        if a is not None and a[0] <= t and (i < 0 or a[0] >= buf.times[i]):
            return i, a[0], a[1]
        if i >= 0 and buf.states[i] is not None:
            return i, buf.times[i], buf.states[i]
        return None

    def _samples_around(self, i: int) -> tuple[tuple, tuple]:
        buf = self._buf
        if i + 1 < len(buf):
            return (buf.samples[i] if i >= 0 else buf.samples[i + 1]), buf.samples[i + 1]
        return buf.samples[i], buf.samples[i]  # past the newest sample: hold its rates

    def _nominal_at(self, t: int) -> FilterState | None:
        """The state at t, its covariance that of the base before t (cheap: for poses)."""
        return self._state_at(t, False)

    def _full_at(self, t: int) -> FilterState | None:
        """The state at t with its covariance propagated to t (for updates)."""
        return self._state_at(t, True)

    def _state_at(self, t: int, with_covariance: bool) -> FilterState | None:
        b = self._base_at(t)
        if b is None:
            return None
        i, base_t, st = b
        if t == base_t or not self._buf.samples:
            return st
        s0, s1 = self._samples_around(i)
        if with_covariance or st.held is not None or not measured(t, s0, s1, self._max_gap_ns):
            return self._step(st, base_t, t, s0, s1)
        return FilterState(step_midpoint(st.x, st.c, base_t, t, s0, s1), st.c, st.cov)

    def _rate_at(self, t: int, st: FilterState) -> tuple:
        """The bias-corrected gyro rate (body) of the newest sample at or before t (in a gap: the rate `st` holds)."""
        if st.held is not None:
            return coasting.rate(st.c)
        c = st.c
        buf = self._buf
        i = max(buf.index_at_or_before(t), 0)
        s = buf.samples[i]
        return (s[1] - c[0], s[2] - c[1], s[3] - c[2])

    def _rate_noise_var(self, t: int) -> float:
        """The variance per axis of one gyro sample's white noise near t: density^2 / interval."""
        times = self._buf.times
        i = max(self._buf.index_at_or_before(t), 0)
        j = i + 1 if i + 1 < len(times) else i
        dt = (times[j] - times[j - 1]) * 1e-9 if j > 0 else 0.0
        return self._prop.densities[0] ** 2 / dt if dt > 0 else 0.0

    def _imu_time(self, t_camera: int) -> int:
        return t_camera + round(self._td * 1e9)

    def _T_CO(self, x: tuple) -> np.ndarray:
        """T_CO = T_CB T_OB^-1 of nominal x, on Python floats (several pose conversions per frame)."""
        b00, b01, b02, b10, b11, b12, b20, b21, b22 = self._R_CB_floats
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = x[0:9]
        px, py, pz = x[9:12]
        c00, c01, c02 = b00 * r00 + b01 * r01 + b02 * r02, b00 * r10 + b01 * r11 + b02 * r12, b00 * r20 + b01 * r21 + b02 * r22
        c10, c11, c12 = b10 * r00 + b11 * r01 + b12 * r02, b10 * r10 + b11 * r11 + b12 * r12, b10 * r20 + b11 * r21 + b12 * r22
        c20, c21, c22 = b20 * r00 + b21 * r01 + b22 * r02, b20 * r10 + b21 * r11 + b22 * r12, b20 * r20 + b21 * r21 + b22 * r22
        tx, ty, tz = self._t_CB_floats
        return np.array([[c00, c01, c02, tx - (c00 * px + c01 * py + c02 * pz)],
                         [c10, c11, c12, ty - (c10 * px + c11 * py + c12 * pz)],
                         [c20, c21, c22, tz - (c20 * px + c21 * py + c22 * pz)],
                         [0.0, 0.0, 0.0, 1.0]])

    def _pose_jacobian(self, st: FilterState, t_imu: int) -> np.ndarray:
        return pose_jacobian(st.x, self._R_CB, self._rate_at(t_imu, st), st.x[12:15])[2]

    def pose_at(self, t_ns: int) -> np.ndarray | None:
        """T_CO at camera time t_ns (None before initialisation; ValueError before the buffer)."""
        t = as_int(t_ns, "t_ns")
        if self._anchor is None:
            return None
        st = self._nominal_at(self._imu_time(t))
        if st is None:
            raise ValueError(f"no state at {t} ns: before tracking started or older than the IMU buffer")
        return self._T_CO(st.x)

    def pose_covariance_at(self, t_ns: int) -> np.ndarray | None:
        """The 6x6 covariance of `pose_at(t_ns)` in the wire convention (rotation first, camera frame)."""
        t = as_int(t_ns, "t_ns")
        if self._anchor is None:
            return None
        t_imu = self._imu_time(t)
        st = self._full_at(t_imu)
        if st is None:
            raise ValueError(f"no state at {t} ns: before tracking started or older than the IMU buffer")
        return _within_wire(pose_covariance(self._pose_jacobian(st, t_imu), st.cov))

    def sigma_px(self, T_CO: np.ndarray, cov: np.ndarray) -> float:
        """RMS over the box corners of the 1-sigma 2D uncertainty (px) a pose covariance implies."""
        RX = np.dot(self._corners_O, T_CO[:3, :3].T)  # (n, 3) corners, rotated
        z = RX[:, 2] + T_CO[2, 3]
        if np.any(z <= 1e-6):
            return float("inf")
        r0, r1, r2 = RX.T
        cam = self.camera
        # d uv / d e = d uv / d X_c [-[R X_o]x, I]: per row d = (d0, 0 or d1, d2), the rotation part is
        # -(d x R X_o). Written column by column: a dozen small numpy operations, not a batched einsum.
        iz = 1.0 / z
        au, cu = cam.fx * iz, -cam.fx * (r0 + T_CO[0, 3]) * iz * iz  # du = (au, 0, cu)
        bv, cv = cam.fy * iz, -cam.fy * (r1 + T_CO[1, 3]) * iz * iz  # dv = (0, bv, cv)
        J = np.zeros((2, len(z), 6))
        J[0, :, 0], J[0, :, 1], J[0, :, 2], J[0, :, 3], J[0, :, 5] = cu * r1, au * r2 - cu * r0, -au * r1, au, cu
        J[1, :, 0], J[1, :, 1], J[1, :, 2], J[1, :, 4], J[1, :, 5] = cv * r1 - bv * r2, -cv * r0, bv * r0, bv, cv
        J = J.reshape(-1, 6)
        return float(np.sqrt(2.0 * np.sum(np.dot(J, cov) * J) / len(J)))

    # ------------------------------------------------------------------ PIM + requests
    def add_frame(self, t_ns: int) -> FrameResult:
        t = as_int(t_ns, "t_ns")
        if self._last_frame_t is not None and t <= self._last_frame_t:
            raise ValueError(f"frame at {t} ns is not after the previous one at {self._last_frame_t} ns")
        o = self.options
        fps = o.fps
        if fps is None and self._last_frame_t is not None:
            fps = 1e9 / (t - self._last_frame_t)
        if self._last_frame_t is not None:
            self._frame_interval_s = (t - self._last_frame_t) * 1e-9
        t_last, self._last_frame_t = self._last_frame_t, t
        if self._anchor is None:
            return self._initializing_frame(t)
        t_imu = self._imu_time(t)
        st = self._full_at(t_imu)  # the covariance propagated to the frame, not the sample before it
        left = self._ease_left(t)
        T_CO = self._eased(self._T_CO(st.x), left)
        # the shown pose is the filter's minus a known offset: its mean-square error about the truth is the
        # filter's covariance plus the offset's outer product (what a NEES of the shown pose must be read on)
        H = self._pose_jacobian(st, t_imu)
        cov = pose_covariance(H, st.cov) + np.outer(left, left)
        if self.error_dynamics is not None:
            self.error_dynamics.frame(t, H @ st.phi)
        status, detail = Status.FINE, "tracking"
        if o.pia:
            uv = self.inspector.project(T_CO)
            status, detail = self.inspector.inspect(uv, self._last_uv_now(t_last), fps)
            self._last_uv = uv
        age_s = (t_imu - self._anchor[0]) * 1e-9
        if status is Status.FINE and o.pia and o.backend_after_init and age_s > o.max_backend_age_s:
            status, detail = Status.TRACKING_LOST, f"no backend pose for {age_s:.1f} s: IMU-only drift"
        if status is Status.FINE and self._rejected:
            status, detail = Status.TRACKING_LOST, "doubtful: the last backend pose disagreed with the filter (gated)"
        if status is Status.FINE:
            sigma = self.sigma_px(T_CO, cov)
            if sigma > o.filter.max_sigma_px:
                status, detail = Status.TRACKING_LOST, f"uncertain: {sigma:.1f} px (1 sigma) > {o.filter.max_sigma_px} px"
        request = None
        if o.backend_after_init and self._book.in_flight is None:
            request = self._book.issue(t, "refine" if status is Status.FINE else "failure")
        self.status, self.status_detail = status, detail
        return FrameResult(t, T_CO, status, request, cov)

    def _ease_left(self, t: int) -> np.ndarray:
        offset, t_set = self._ease
        fo = self.options.filter
        if fo.ease_s <= 0:
            return offset * 0.0
        tau = max(fo.ease_s, fo.ease_min_frames * self._frame_interval_s)
        return offset * np.exp(-(t - t_set) * 1e-9 / tau)

    def _eased(self, T_CO: np.ndarray, o: np.ndarray) -> np.ndarray:
        """The pose shown: the filter's, minus `o`, what is left at the frame's time of its recent corrections
        (`FilterOptions.ease_s`), so that a correction glides in over a few frames instead of jumping."""
        if not o.any():
            return T_CO
        T = T_CO.copy()
        ox, oy, oz = o[0:3].tolist()
        # Exp(-o) R = (R^T Exp(o))^T, on floats (`propagation.rotate` right-multiplies)
        T[:3, :3] = np.array(rotate(tuple(T_CO[:3, :3].T.ravel().tolist()), ox, oy, oz)).reshape(3, 3).T
        T[:3, 3] = T_CO[:3, 3] - o[3:6]
        return T

    def _last_uv_now(self, t_last: int | None) -> np.ndarray | None:
        """The last frame's corners, re-evaluated on the corrected trajectory after an update (the
        correction's own jump is no failure of the PIA's motion test)."""
        if not self._corrected:
            return self._last_uv
        self._corrected = False
        if t_last is None or self._last_uv is None:
            return None
        st = self._nominal_at(self._imu_time(t_last))
        return None if st is None else self.inspector.project(self._T_CO(st.x))

    # ------------------------------------------------------------------ refinement
    def on_backend_response(self, request_id: int, capture_t_ns: int, T_CO: np.ndarray | None, ok: bool = True,
                            covariance: np.ndarray | None = None) -> ResponseOutcome:
        """Update the filter with the backend's T_CO (and its 6x6 covariance, wire convention) at the capture
        time, then re-propagate the buffered IMU to now. ValueError, with no state change, for a capture
        time that is not the request's, a pose that is not rigid, or a covariance that is not SPD."""
        t0 = self._answered(request_id, capture_t_ns)
        if t0 is None:
            return ResponseOutcome.STALE
        usable = ok and T_CO is not None
        if usable:
            T = np.array(check_rigid(T_CO, "T_CO")).reshape(4, 4)
            sigma = None if covariance is None else wire.check_covariance(covariance, "covariance")
        self._book.in_flight = None
        if not usable:
            return self._outcome(ResponseOutcome.REJECTED, "backend found no pose; asking again")
        fo = self.options.filter
        note = ""
        if sigma is None or not fo.use_backend_covariance:
            note = "" if sigma is not None else " (no covariance from the backend: the default used)"
            sigma = self._default_sigma
        floor = self._floor_var - np.diagonal(sigma)
        if (floor > 0).any():  # what no backend can know better than the tracker can use (FilterOptions.answer_floor_*)
            sigma = sigma + np.diag(np.maximum(floor, 0.0))
        tau = self._imu_time(t0)
        buf = self._buf
        if not len(buf) or tau < buf.first_t_ns or (self._anchor is not None and self._base_at(tau) is None):
            return self._outcome(ResponseOutcome.TOO_OLD, "backend pose older than the IMU buffer; dropped")
        if self._anchor is not None and tau < self._anchor[0]:  # the states before it predate the last update
            return self._outcome(ResponseOutcome.TOO_OLD, "backend pose older than the last one applied; dropped")
        if self._anchor is None:
            self._initialize(tau, T, sigma)
            return self._outcome(ResponseOutcome.INITIALIZED, "tracking: initialised from the first backend pose" + note)
        st = self._full_at(tau)
        age_s = (tau - self._anchor[0]) * NS
        if st.held is not None and age_s > self.options.max_backend_age_s:
            self._initialize(tau, T, sigma)  # the answers alone carried the pose; without them it is gone
            return self._outcome(ResponseOutcome.INITIALIZED, f"no backend pose for {age_s:.1f} s in a gap of the "
                                 "IMU's stream: re-initialised from the backend's pose")
        in_gap = st.held is not None
        res = update(st, self._td, T, sigma, self._R_CB, self._t_CB, self._rate_at(tau, st),
                     0.0 if in_gap else self._rate_noise_var(tau), fo.gate_chi2, fo.gravity_state,
                     offset_observable=not in_gap)
        measured = not in_gap and self._measured_since(self._anchor[0])
        if measured:  # how long the IMU alone carried the pose, from the last answer's capture to now
            self._prop.note_answer_interval((buf.last_t_ns - self._anchor[0]) * NS)
        self._match_noise(res, st, age_s, measured)
        if not res.accepted:
            self._rejected += 1
            if self._rejected < fo.max_rejections:
                return self._outcome(ResponseOutcome.GATED, f"backend pose rejected (chi2 {res.chi2:.1f} > "
                                     f"{fo.gate_chi2}; {self._rejected} in a row)")
            rejected = self._rejected
            self._initialize(tau, T, sigma)
            return self._outcome(ResponseOutcome.INITIALIZED, f"{rejected} backend poses rejected in a row: "
                                 "the filter was wrong; re-initialised from the backend's pose")
        self._rejected = 0
        t_shown = self._last_frame_t
        before = self._T_CO(self._nominal_at(self._imu_time(t_shown)).x) if t_shown is not None else None
        self._td = res.td
        new = res.state
        if self.error_dynamics is not None:
            self.error_dynamics.link(res.closed_loop @ st.phi, new.cov)
            new = replace(new, phi=np.eye(new.cov.shape[0]))
        self._set_anchor(tau, new)
        if before is not None and fo.ease_s > 0:
            after = self._T_CO(self._nominal_at(self._imu_time(t_shown)).x)
            jump = np.concatenate([so3.log(after[:3, :3] @ before[:3, :3].T), after[:3, 3] - before[:3, 3]])
            self._ease = (self._ease_left(t_shown) + jump, t_shown)
        return self._outcome(ResponseOutcome.APPLIED, "tracking" + note)

    def _match_noise(self, res, st: FilterState, dt: float, measured: bool) -> None:
        """Feed an answer's innovation to the noise fits and use what they say: the IMU's (`eskf.noise_matching`)
        when the IMU measured everything since the last answer, the hand motion's (`eskf.coasting`) when both
        answers lie in one gap of its stream, none across a gap's edge. A gated answer counts as one on the
        gate (an outlier's size says nothing of the noise; that the filter gated it may: too little process
        noise); the first SETTLE_ANSWERS after a (re-)initialisation not at all (a start's transient is no
        noise: a simulated 8 s run at 30 FPS had its densities raised by it). `measured`: the IMU measured
        everything since the last answer."""
        self._since_start += 1
        if res.residual is None:
            return
        shrink = min(1.0, self.options.filter.gate_chi2 / res.chi2) if res.chi2 > 0 else 1.0
        anchor = self._anchor[1]
        if st.held is not None:
            if anchor.held is not None and anchor.held[2] == st.held[2]:
                Rp = self._t_CB - self._T_CO(st.x)[:3, 3]
                self._gap_noise.add(res.residual * shrink ** 0.5, res.S, Rp, dt)
            return
        if self._since_start <= SETTLE_ANSWERS or self._matchers is None or anchor.held is not None or not measured:
            return
        now = self._prop.densities
        for m, d, (r2, trace_s, trace_s2) in zip(self._matchers, now, blocks(res.residual, res.S)):
            m.add(r2 * shrink, trace_s, d, dt, trace_s2)
        self._prop.match(self._matchers[0].density, self._matchers[1].density)

    def _measured_since(self, t: int) -> bool:
        """Whether the IMU measured everything from t to the newest sample (no gap in its stream)."""
        times, gap = self._buf.times, self._max_gap_ns
        i = max(self._buf.index_at_or_before(t), 0)
        return all(times[k + 1] - times[k] <= gap for k in range(i, len(times) - 1))

    def _initialize(self, tau: int, T_CO: np.ndarray, sigma: np.ndarray) -> None:
        T_OB = np.linalg.inv(T_CO) @ np.vstack([np.hstack([self._R_CB, self._t_CB[:, None]]), [0, 0, 0, 1]])
        x_pose = tuple(T_OB[:3, :3].ravel().tolist()) + tuple(T_OB[:3, 3].tolist())
        window_ns = round(self.options.init_window_s * 1e9)
        at_tau = self._buf.samples[max(self._buf.index_at_or_before(tau), 0)]  # the sample at or before tau
        window = self._buf.window(tau - window_ns, tau) or [at_tau]
        est = initialization.estimate(window, self.options)
        in_gap = len(window) < 2 or tau - window[-1][0] > self._max_gap_ns  # nothing measured at tau
        if in_gap:
            est = replace(est, still=False)
        before = self._full_at(tau) if in_gap and self._anchor is not None else None
        self._rejected = 0
        self._since_start = 0
        # the time offset is the device's, not the track's: a re-initialisation keeps the estimate and its sigma
        td_std = None if self._anchor is None else float(self._anchor[1].cov[TD, TD]) ** 0.5
        self._anchor = None
        st = initial_state(x_pose, sigma, window, self._R_CB, est, self.options.filter, gyro=at_tau[1:4],
                           gyro_var=self._rate_noise_var(tau), td_std=td_std)
        if before is not None:
            st = _carried(st, before)
        if self.error_dynamics is not None:
            self.error_dynamics.restart(st.cov)
            st = replace(st, phi=np.eye(st.cov.shape[0]))
        self._set_anchor(tau, st)

    def _set_anchor(self, tau: int, st: FilterState) -> None:
        """The state at tau from an answer; every buffered sample after tau re-propagated from it."""
        self._anchor = (tau, st)
        buf = self._buf
        start = buf.index_at_or_before(tau) + 1
        prev = buf.samples[start - 1] if start > 0 else None
        t = tau
        for i in range(start, len(buf)):
            s = buf.samples[i]
            st = self._step(st, t, s[0], prev if prev is not None else s, s)
            buf.states[i] = st
            t, prev = s[0], s
        self._corrected = True

    # ------------------------------------------------------------------ wire state
    def state_bytes(self) -> bytes:
        """As `Tracker.state_bytes`: the state and the newest IMU samples, ~10 kB."""
        return state_codec.blob(self.state, self.now_ns, self._buf, self.options.state_imu_samples)
