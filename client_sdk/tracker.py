"""The tracker core: a synchronous, deterministic state machine fed with events.

    tracker = Tracker(TrackerOptions(), camera, T_BC, bbox_corners_O)
    tracker.add_imu(t_ns, gyro, accel)          # PPM: propagate, keep the sample
    result = tracker.add_frame(t_ns)            # pose + PIM status; maybe a RefinementRequest
    if result.request: send that frame to the backend, then later
    tracker.on_backend_response(request_id, capture_t_ns, T_CO, ok)   # PRM + BSCM + re-propagation
    tracker.on_backend_failure(request_id)      # lost / timed out: the next frame asks again
    tracker.pose_at(t_ns)                       # T_CO at any time up to now, for any frame rate

No threads, sockets, sleeps or clocks: time is what the events say. The same events give the same
outputs, bit for bit. docs/tracker.md explains the state, the decisions and the options.

PRM reset on a PIM failure (WRONG_POSE or TRACKING_LOST), precisely: the BSCM reference (the last
backend pose) is forgotten and the velocity marked unknown, so the next backend pose only resets
orientation and position, the one after it sets the velocity outright from the two poses (V_avg
carried to the capture time, biases untouched), and regular BSCM resumes with the third; a request in flight that was sent regularly is abandoned (its response will be
STALE) and a new request for the failing frame goes out at once (reason "failure"); a request that
was itself sent because of a failure is kept, so a run of failing frames sends one request at a
time. The reset happens once, on entering a failure: frames that go on failing do not reset it
again, so the poses that arrive meanwhile can re-estimate the velocity (resetting at every failing
frame would keep a wrong velocity, and with it the failure, for ever). The biases and gravity are
kept: they belong to the IMU, not to the pose. A backend pose
that disagrees with the IMU beyond belief (`bscm_max_velocity_error`, `bscm_max_rotation_rate`)
is still applied (the paper trusts the backend; the PIM catches it if it is wrong) but resets the
PRM in the same way instead of feeding BSCM; so does a velocity set outright from two poses that
implies more than `max_speed_m_s`. With `backend_gate_px` set, a pose far from the tracked one
while tracking is FINE is not applied at all (GATED), up to `backend_gate_rejects` in a row.
"""

from __future__ import annotations

from math import sqrt

import numpy as np

from client_sdk import state as state_codec
from client_sdk.imu_buffer import ImuBuffer
from client_sdk.inspection import PoseInspector, Status
from client_sdk.options import TrackerOptions
from client_sdk.propagation import INTEGRATOR_STEPS, propagate
from client_sdk.refinement import BscmResult, ResponseOutcome, blend_pose, bscm
from client_sdk.state import TrackerState
from client_sdk.tracker_base import FrameResult, TrackerBase, as_int, check_rigid, imu_sample
from flextrack.geometry import se3
from flextrack.geometry.camera import PinholeCamera


def _rot(R: tuple, u: tuple) -> tuple:
    """R u for R the first 9 floats (row-major) of a tuple."""
    return (R[0] * u[0] + R[1] * u[1] + R[2] * u[2], R[3] * u[0] + R[4] * u[1] + R[5] * u[2],
            R[6] * u[0] + R[7] * u[1] + R[8] * u[2])


def _rot_t(R: tuple, u: tuple) -> tuple:
    """R^T u for R the first 9 floats (row-major) of a tuple."""
    return (R[0] * u[0] + R[3] * u[1] + R[6] * u[2], R[1] * u[0] + R[4] * u[1] + R[7] * u[2],
            R[2] * u[0] + R[5] * u[1] + R[8] * u[2])


class Tracker(TrackerBase):
    """The paper's device side: PPM, PIM (PIA) and PRM (BSCM) around one state. See module doc."""

    def __init__(self, options: TrackerOptions | None, camera: PinholeCamera, T_BC: np.ndarray,
                 bbox_corners_O: np.ndarray) -> None:
        super().__init__()
        self.options = options if options is not None else TrackerOptions()
        self._assess_options = o = self.options
        T_CB = se3.inverse(np.array(check_rigid(T_BC, "T_BC")).reshape(4, 4))
        # plain floats: the per-frame and per-response pose conversions are written out on them
        self._R_CB_f, self._t_CB_f = tuple(T_CB[:3, :3].ravel().tolist()), tuple(T_CB[:3, 3].tolist())
        self.camera = camera
        self.inspector = PoseInspector(camera, bbox_corners_O, o.area_divisor, o.px_error, o.px_motion,
                                       o.base_rate, o.near_m)
        self._step = INTEGRATOR_STEPS[o.integrator]
        self._buf = ImuBuffer(round(o.imu_buffer_s * 1e9))
        self._c: tuple | None = None  # (b_g, b_a, g_O); None until initialised
        self._anchor_t: int | None = None  # the last state set from a backend pose ...
        self._anchor_x: tuple | None = None  # ... (nominal tuple) at its capture time
        self._ref: tuple[int, tuple] | None = None  # (t_ns, p_OB) of the last backend pose, for BSCM
        self._velocity_known = False  # False after a PRM reset: the next BSCM re-estimates v outright
        self._last_frame_t: int | None = None
        self._last_uv: np.ndarray | None = None
        self._corrected = False  # a backend pose was applied since the last frame
        self._failing = False  # the last frame failed the PIA (the PRM was reset on entering that)
        self._gated = 0  # backend poses gated in a row
        self.last_bscm: BscmResult | None = None

    # ------------------------------------------------------------------ properties
    @property
    def initialized(self) -> bool:
        return self._c is not None

    @property
    def now_ns(self) -> int | None:
        """The newest time the tracker knows of (last IMU sample or backend capture time)."""
        last = self._buf.last_t_ns
        if self._anchor_t is None:
            return last
        return self._anchor_t if last is None else max(last, self._anchor_t)

    @property
    def state(self) -> TrackerState | None:
        """A copy of the state at `now_ns` (None before initialisation)."""
        if self._c is None:
            return None
        t = self.now_ns
        return TrackerState.from_tuples(t, self._state_at(t), self._c)

    # ------------------------------------------------------------------ PPM
    def add_imu(self, t_ns: int, gyro, accel) -> None:
        """Propagate the state to this IMU sample (rad/s, m/s^2, body frame) and keep the sample.

        ValueError, with no state change, for non-finite values or a time not after the previous one.
        """
        buf = self._buf
        last = buf.last_t_ns
        s = imu_sample(t_ns, gyro, accel, last)
        t = s[0]
        x = None
        if self._c is not None:
            if last is None or self._anchor_t >= last:  # first sample after a backend pose
                x = self._step(self._anchor_x, self._c, self._anchor_t, t, buf.samples[-1] if buf.samples else s, s)
            else:
                x = self._step(buf.states[-1], self._c, last, t, buf.samples[-1], s)
        buf.append(s, x)

    def _state_at(self, t: int) -> tuple | None:
        """Nominal tuple at t: from the anchor or the stored state before t, stepped to t."""
        buf = self._buf
        i = buf.index_at_or_before(t)
        a = self._anchor_t
        if a is not None and a <= t and (i < 0 or a >= buf.times[i]):
            base_t, x = a, self._anchor_x
        elif i >= 0 and buf.states[i] is not None:
            base_t, x = buf.times[i], buf.states[i]
        else:
            return None
        if t == base_t or not buf.samples:
            return x
        if i + 1 < len(buf):
            s1 = buf.samples[i + 1]
            s0 = buf.samples[i] if i >= 0 else s1
        else:  # past the newest sample: hold its rates
            s0 = s1 = buf.samples[i]
        return self._step(x, self._c, base_t, t, s0, s1)

    def _T_CO(self, x: tuple) -> np.ndarray:
        """T_CO = T_CB T_BO of a nominal tuple: R_CO = R_CB R_OB^T, t_CO = t_CB - R_CO p_OB."""
        a0, a1, a2, a3, a4, a5, a6, a7, a8 = self._R_CB_f
        r0, r1, r2, r3, r4, r5, r6, r7, r8, px, py, pz = x[0:12]
        c0, c1, c2 = a0 * r0 + a1 * r1 + a2 * r2, a0 * r3 + a1 * r4 + a2 * r5, a0 * r6 + a1 * r7 + a2 * r8
        c3, c4, c5 = a3 * r0 + a4 * r1 + a5 * r2, a3 * r3 + a4 * r4 + a5 * r5, a3 * r6 + a4 * r7 + a5 * r8
        c6, c7, c8 = a6 * r0 + a7 * r1 + a8 * r2, a6 * r3 + a7 * r4 + a8 * r5, a6 * r6 + a7 * r7 + a8 * r8
        tx, ty, tz = self._t_CB_f
        return np.array([
            c0, c1, c2, tx - (c0 * px + c1 * py + c2 * pz),
            c3, c4, c5, ty - (c3 * px + c4 * py + c5 * pz),
            c6, c7, c8, tz - (c6 * px + c7 * py + c8 * pz),
            0.0, 0.0, 0.0, 1.0,
        ]).reshape(4, 4)

    def pose_at(self, t_ns: int) -> np.ndarray | None:
        """T_CO at t_ns: re-propagated from the stored state before it, extrapolated past the newest
        IMU sample with its rates held. None before initialisation; ValueError for times older than
        the IMU buffer or before tracking started."""
        t = as_int(t_ns, "t_ns")
        if self._c is None:
            return None
        x = self._state_at(t)
        if x is None:
            raise ValueError(f"no state at {t} ns: before tracking started or older than the IMU buffer")
        return self._T_CO(x)

    # ------------------------------------------------------------------ PIM + PRM requests
    def add_frame(self, t_ns: int) -> FrameResult:
        """The pose at this frame, its PIA status, and the backend request the PRM wants sent (if any)."""
        t = as_int(t_ns, "t_ns")
        if self._last_frame_t is not None and t <= self._last_frame_t:
            raise ValueError(f"frame at {t} ns is not after the previous one at {self._last_frame_t} ns")
        fps = self.options.fps
        if fps is None and self._last_frame_t is not None:
            fps = 1e9 / (t - self._last_frame_t)  # the last interval: a dropped frame widens THR_2d
        t_last, self._last_frame_t = self._last_frame_t, t
        if self._c is None:
            return self._initializing_frame(t)

        T_CO = self._T_CO(self._state_at(t))
        if self.options.pia:
            uv = self.inspector.project(T_CO)
            status, detail = self.inspector.inspect(uv, self._last_uv_now(t_last), fps)
            self._last_uv = uv
            age_s = (t - self._anchor_t) * 1e-9
            if status is Status.FINE and self.options.backend_after_init and age_s > self.options.max_backend_age_s:
                status, detail = Status.TRACKING_LOST, f"no backend pose for {age_s:.1f} s: IMU-only drift"
        else:
            status, detail = Status.FINE, "tracking"
        failed = status is not Status.FINE
        if failed and not self._failing:  # entering a failure: the PIM re-initialises the PRM (module doc)
            self._ref, self._velocity_known = None, False
            if self._book.in_flight is not None and self._book.in_flight.reason != "failure":
                self._book.in_flight = None
        self._failing = failed
        request = None
        if self.options.backend_after_init and self._book.in_flight is None:
            request = self._book.issue(t, "failure" if failed else "refine")
        self.status, self.status_detail = status, detail
        return FrameResult(t, T_CO, status, request)

    def _last_uv_now(self, t_last: int | None) -> np.ndarray | None:
        """The last frame's corners. After a backend correction, re-evaluated on the corrected
        trajectory: the PIA measures motion between frames, and the correction's own jump (the
        error it removes) is no failure; comparing against the stale pose would flag every large
        fix as WRONG_POSE and, through the PRM reset, keep the velocity from ever being re-estimated."""
        if not self._corrected:
            return self._last_uv
        self._corrected = False
        x = self._state_at(t_last) if t_last is not None and self._last_uv is not None else None
        if x is None:
            return None
        return self.inspector.project(self._T_CO(x))

    # ------------------------------------------------------------------ PRM responses
    def on_backend_response(self, request_id: int, capture_t_ns: int, T_CO: np.ndarray | None,
                            ok: bool = True, covariance: np.ndarray | None = None) -> ResponseOutcome:
        """Apply the backend's T_CO at capture time t0: state at t0 from it, BSCM, re-propagation to now.
        The paper's method has no use for the answer's `covariance` (the filter's has).

        ValueError, with no state change, when the capture time differs from the request's frame
        time or the pose is not a rigid transform.
        """
        t0 = self._answered(request_id, capture_t_ns)
        if t0 is None:
            return ResponseOutcome.STALE
        usable = ok and T_CO is not None
        if usable:
            T_CO = check_rigid(T_CO, "T_CO")
        self._book.in_flight = None
        if not usable:
            return self._outcome(ResponseOutcome.REJECTED, "backend found no pose; asking again")
        buf = self._buf
        if not len(buf) or t0 < buf.first_t_ns or (self._c is not None and self._state_at(t0) is None):
            return self._outcome(ResponseOutcome.TOO_OLD, "backend pose older than the IMU buffer; dropped")

        R, p, u = self._body_pose(T_CO)
        detail = "tracking"
        if self._c is None:
            est = self._init_est
            g_O = (np.array(R).reshape(3, 3) @ est.g_B).tolist()
            self._c = tuple(est.b_g.tolist()) + (0.0, 0.0, 0.0) + tuple(g_O)
            self._anchor_t, self._anchor_x = t0, R + p + (0.0, 0.0, 0.0)
            self._velocity_known = est.still  # a still device: v = 0 is exact
            self._ref = (t0, p)
            outcome = ResponseOutcome.INITIALIZED
        else:
            x_imu = self._state_at(t0)
            v = x_imu[12:15]
            o = self.options
            jump = self._gate_distance(x_imu, T_CO)
            if jump is not None and self._gated < o.backend_gate_rejects:
                self._gated += 1
                return self._outcome(ResponseOutcome.GATED, f"backend pose {jump:.0f} px from the tracked pose: "
                                     f"ignored ({self._gated} in a row)")
            # The gate gives way: the backend keeps disagreeing, so the tracker is the one that is wrong,
            # most likely since a wrong first pose. Its gravity came from that pose's orientation: it
            # follows the correction (the body-frame gravity, which the IMU measured, is kept).
            regravitate = reset = jump is not None
            self._gated = 0
            keep_ref = False
            if o.bscm and self._ref is not None and not regravitate:
                t_ref, p_ref = self._ref
                dt = (t0 - t_ref) * 1e-9
                x_mid = self._state_at((t_ref + t0) // 2)
                # closer than the minimum baseline: wait, keeping the reference, so that V_avg (whose
                # noise is the backend's position noise / dt) always spans at least that baseline
                keep_ref = dt < o.bscm_min_interval_s
                if o.bscm_min_interval_s <= dt <= o.bscm_max_interval_s and x_mid is not None:
                    p_vel = _rot(x_imu, u) if o.bscm_imu_orientation else p
                    speed = 0.0
                    if self._velocity_known:
                        gains = (o.gyro_bias_gain, o.accel_bias_gain, o.velocity_gain, o.bscm_max_velocity_error,
                                 o.bscm_max_rotation_rate)
                    else:  # first BSCM after a PRM reset: velocity outright from the two poses, biases kept
                        gains = (0.0, 0.0, 1.0, float("inf"), float("inf"))
                        speed = sqrt(sum((p_vel[k] - p_ref[k]) ** 2 for k in range(3))) / dt
                    if speed > o.max_speed_m_s:
                        reset = True
                        detail = f"two backend poses imply {speed:.1f} m/s: one is wrong; PRM reset"
                    else:
                        res = bscm(self._c, x_imu, R, p_vel, p_ref, x_mid, dt, gains[0], gains[1], gains[2],
                                   o.max_gyro_bias, o.max_accel_bias, gains[3], gains[4],
                                   dt_rot=(t0 - self._anchor_t) * 1e-9)
                        self.last_bscm = res
                        if res.accepted:
                            self._c, v, self._velocity_known = res.c, res.v, True
                        else:  # backend and IMU disagree beyond belief: reset the PRM, keep the pose
                            reset = True
                            detail = "backend pose disagrees with the IMU: BSCM skipped, PRM reset"
            R_set, p_set = blend_pose(x_imu, R, p, o.pose_gain)
            if regravitate:  # the whole pose; the velocity, propagated with the wrong gravity, starts again at 0
                R_set, p_set, v = R, p, (0.0, 0.0, 0.0)
                detail = "the backend kept disagreeing: its pose applied, gravity re-anchored, PRM reset"
            self._follow_gravity(x_imu, R_set, 1.0 if regravitate else o.gravity_follow)
            self._anchor_t, self._anchor_x = t0, R_set + p_set + tuple(v)
            # the reference for the next V_avg, in the same terms as p_vel will be then
            if not keep_ref:
                self._ref = None if reset else (t0, _rot(R_set, u) if o.bscm_imu_orientation else p)
            self._velocity_known = self._velocity_known and not reset
            outcome = ResponseOutcome.APPLIED
            self._corrected = True
        propagate(self._step, self._anchor_x, self._c, t0, buf.samples, buf.states, buf.index_at_or_before(t0) + 1)
        return self._outcome(outcome, detail)

    def _follow_gravity(self, x_imu: tuple, R_set: tuple, k: float) -> None:
        """Move g_O a fraction k of the way to where the orientation change x_imu -> R_set carries it
        (k = 1 keeps the body-frame gravity exactly; TrackerOptions.gravity_follow), keeping its norm."""
        if k <= 0:
            return
        g_old = self._c[6:9]
        g_new = _rot(R_set, _rot_t(x_imu, g_old))
        g = tuple((1 - k) * g_old[i] + k * g_new[i] for i in range(3))
        scale = sqrt(sum(e * e for e in g_old)) / sqrt(sum(e * e for e in g))
        self._c = self._c[0:6] + tuple(e * scale for e in g)

    def _gate_distance(self, x_imu: tuple, T_CO: list[float]) -> float | None:
        """The mean box-corner distance (px) between the backend's pose and the tracked one at the
        capture time when it is beyond the backend gate (and the gate applies), else None. A pose with
        a box corner behind the camera has no such distance: it counts as infinitely far."""
        o = self.options
        if not (o.backend_gate_px > 0 and self.status is Status.FINE and self._velocity_known):
            return None
        uv_tracked = self.inspector.project(self._T_CO(x_imu))
        uv_backend = self.inspector.project(np.array(T_CO).reshape(4, 4))
        if uv_tracked is None or uv_backend is None:
            return float("inf")
        jump = float(np.mean(np.linalg.norm(uv_backend - uv_tracked, axis=1)))
        return None if jump <= o.backend_gate_px else jump

    def _body_pose(self, m: list[float]) -> tuple[tuple, tuple, tuple]:
        """(R_OB, p_OB, u) as float tuples of T_OB = T_CO^-1 T_CB, T_CO given as 16 row-major floats;
        u = R_CB^T (t_CB - t_CO) is such that p_OB = R_OB u for any R_OB (used for V_avg)."""
        A = self._R_CB_f  # R_OB = R_CO^T R_CB
        R = tuple(m[k] * A[j] + m[4 + k] * A[3 + j] + m[8 + k] * A[6 + j] for k in range(3) for j in range(3))
        d = [self._t_CB_f[i] - m[4 * i + 3] for i in range(3)]  # p_OB = R_CO^T (t_CB - t_CO)
        p = tuple(m[k] * d[0] + m[4 + k] * d[1] + m[8 + k] * d[2] for k in range(3))
        u = tuple(A[k] * d[0] + A[3 + k] * d[1] + A[6 + k] * d[2] for k in range(3))
        return R, p, u

    # ------------------------------------------------------------------ wire state
    def state_bytes(self) -> bytes:
        """The state and the newest `state_imu_samples` IMU samples, float64 (~10 kB by default),
        for the transport to attach as `client_state`; `client_sdk.state.decode` reads it back.
        Before initialisation the state part is identity / zeros at the newest IMU time."""
        return state_codec.blob(self.state, self.now_ns, self._buf, self.options.state_imu_samples)
