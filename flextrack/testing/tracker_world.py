"""A small analytic world for the tracker core's tests and benchmark (independent of the simulator).

The IMU body circles a box-shaped object (20 x 16 x 12 cm) at 1.2 m as in the paper's scene, at
about the paper's "circular hard" speed (0.25 m/s), looking at it, with a varying orbit rate, a
wobble of the orientation and a vertical bob; it is still for `still_s` seconds first (the paper's
initialisation) and ramps into motion smoothly. The object frame is tilted against gravity so that
g_O is not along an axis. IMU readings are the exact body rate and specific force (central
differences of the analytic pose, accurate to ~1e-8), plus optional constant biases and seeded noise.
An event loop drives a Tracker with a ground-truth backend that answers after a fixed latency.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from client_sdk import Tracker, TrackerOptions, create_tracker
from flextrack.geometry import se3, so3
from flextrack.geometry.camera import PinholeCamera, bbox_corners

G_O = so3.exp(np.array([0.1, -0.05, 0.0])) @ np.array([0.0, 0.0, -9.81])
T_BC = se3.make(so3.exp(np.array([0.02, -0.01, 0.03])), np.array([0.01, -0.005, 0.002]))
BOX_O = bbox_corners(np.array([[-0.1, -0.08, -0.06], [0.1, 0.08, 0.06]]))
CAMERA = PinholeCamera.linemod()
# camera axes in O when the body is at orbit angle 0: x = +y_O, y (down) = -z_O, z (forward) = -x_O
_R_OC0 = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
_A = _R_OC0 @ T_BC[:3, :3].T  # R_OB at orbit angle 0
_WOBBLE_AXIS = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])


def _ramp(t: float, start: float, length: float) -> tuple[float, float]:
    """(e, integral of e) for e a C2 smootherstep from 0 (t <= start) to 1 (t >= start + length)."""
    x = min(max((t - start) / length, 0.0), 1.0)
    e = x**3 * (10 - 15 * x + 6 * x * x)
    q = length * (x**6 - 3 * x**5 + 2.5 * x**4) + max(t - start - length, 0.0)
    return e, q


@dataclass
class Motion:
    still_s: float = 1.0
    ramp_s: float = 1.0
    radius: float = 1.2
    rate: float = 0.2  # orbit rate, rad/s
    wobble: float = 0.05  # rad
    bob: float = 0.03  # m

    def body_pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(R_OB, p_OB) at t seconds."""
        e, q = _ramp(t, self.still_s, self.ramp_s)
        tm = q  # "moving time": 0 while still
        psi = self.rate * tm + 0.2 * np.sin(1.5 * tm)
        theta = e * self.wobble * np.sin(2.3 * tm)
        R = so3.exp(np.array([0.0, 0.0, psi])) @ _A @ so3.exp(theta * _WOBBLE_AXIS)
        r = self.radius
        p = np.array([r * np.cos(psi), r * np.sin(psi), e * self.bob * np.sin(1.1 * tm)])
        return R, p

    def T_CO(self, t: float) -> np.ndarray:
        R, p = self.body_pose(t)
        return se3.inverse(se3.make(R, p) @ T_BC)

    def imu(self, t: float, h: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
        """Exact (to ~1e-8) body angular rate and specific force at t."""
        Rm, pm = self.body_pose(t - h)
        R, p = self.body_pose(t)
        Rp, pp = self.body_pose(t + h)
        w = so3.log(Rm.T @ Rp) / (2 * h)
        a_O = (pp - 2 * p + pm) / (h * h)
        return w, R.T @ (a_O - G_O)


@dataclass
class Run:
    times_ns: np.ndarray  # frame times
    poses: list  # FrameResult.T_CO per frame
    statuses: list
    results: list
    tracker: Tracker


def drive(motion: Motion, options: TrackerOptions | None = None, duration_s: float = 4.0, fps: float = 60.0,
          imu_hz: float = 200.0, latency_s: float = 0.05, b_g=(0.0, 0.0, 0.0), b_a=(0.0, 0.0, 0.0),
          gyro_sigma: float = 0.0, accel_sigma: float = 0.0, seed: int = 0, answer=None,
          bias_from_s: float = 0.0, imu_log: list | None = None, answer_covariance=None,
          imu_delay_s: float = 0.0, gyro_scale=None) -> Run:
    """Feed IMU, frames and ground-truth backend responses (after `latency_s`) in time order to the
    tracker core `options.fusion` names.

    The biases are added from `bias_from_s` on. `answer(t_capture_s) -> T_CO or None` replaces the
    ground-truth backend when given; `answer_covariance` (6x6) goes with every answer. The IMU
    stamps each sample `imu_delay_s` late (a camera-IMU time offset). `gyro_scale` (3x3 M), when given, makes
    the gyro read (I + M) times the true rate (a scale-and-misalignment error). `imu_log`, when given,
    receives every (t_ns, gyro, accel) fed.
    """
    rng = np.random.default_rng(seed)
    tracker = create_tracker(options or TrackerOptions(), CAMERA, T_BC, BOX_O)
    delay = round(imu_delay_s * 1e9)
    imu_ns = np.arange(1, int(duration_s * imu_hz) + 1) * round(1e9 / imu_hz)
    frame_ns = np.arange(1, int(duration_s * fps)) * round(1e9 / fps) + 1_000_000  # off the IMU grid
    events = [(int(t) + delay, 0, "imu") for t in imu_ns] + [(int(t), 2, "frame") for t in frame_ns]
    events.sort()
    pending: list[tuple[int, int, int]] = []  # (due_ns, request_id, capture_ns)
    poses, statuses, results = [], [], []
    lat = round(latency_s * 1e9)
    for t, _, kind in events:
        while pending and pending[0][0] <= t:
            _, rid, cap = pending.pop(0)
            T = answer(cap * 1e-9) if answer else motion.T_CO(cap * 1e-9)
            tracker.on_backend_response(rid, cap, T, T is not None, answer_covariance)
        if kind == "imu":
            w, f = motion.imu((t - delay) * 1e-9)
            on = 1.0 if (t - delay) * 1e-9 >= bias_from_s else 0.0
            if gyro_scale is not None:
                w = w + np.asarray(gyro_scale) @ w
            w = w + on * np.asarray(b_g) + gyro_sigma * rng.standard_normal(3)
            f = f + on * np.asarray(b_a) + accel_sigma * rng.standard_normal(3)
            tracker.add_imu(t, w, f)
            if imu_log is not None:
                imu_log.append((t, w, f))
        else:
            r = tracker.add_frame(t)
            results.append(r)
            poses.append(r.T_CO)
            statuses.append(r.status)
            if r.request is not None:
                pending.append((t + lat, r.request.request_id, r.request.frame_t_ns))
    return Run(frame_ns, poses, statuses, results, tracker)


def noisy_answers(motion: Motion, sigma_deg: float, seed: int, sigma_m: float = 0.003):
    """A backend answer(t_s): the true T_CO with Gaussian rotation (deg, left, camera frame) and
    translation (m) noise per axis, as the noisy oracle draws it."""
    rng = np.random.default_rng(seed)

    def answer(t):
        T = motion.T_CO(t)
        return se3.make(so3.exp(np.radians(sigma_deg) * rng.standard_normal(3)) @ T[:3, :3],
                        T[:3, 3] + sigma_m * rng.standard_normal(3))

    return answer
