"""Every knob of the tracker core in one plain dataclass (defaults follow the paper where it gives one).

`fusion` picks the refinement: "filter" (the default: an error-state Kalman filter, its options in
`filter`, nothing tuned per backend) or "paper" (the paper's PRM + BSCM with the gains below, kept
for the paper's tables and the ablation). The PIA, the request policy and initialisation's window
are shared.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from client_sdk.eskf.options import FilterOptions

INTEGRATORS = ("paper", "midpoint")
FUSIONS = ("filter", "paper")
PRESETS = ("filter", "paper")


@dataclass
class TrackerOptions:
    """Options of the tracker core (`client_sdk.create_tracker`); invalid values raise ValueError when built."""

    fusion: str = "filter"
    """"filter": the error-state Kalman filter (`client_sdk.eskf`, options in `filter`). "paper": the
    paper's PRM and BSCM (the options from `integrator` to `bscm_max_interval_s` below)."""
    filter: FilterOptions = field(default_factory=FilterOptions)
    """The filter's noise models, initial uncertainties, gate and status threshold."""

    # --- PPM: propagation ---
    integrator: str = "paper"
    """"paper": the paper's Eqs. 2-7 (rotation, then velocity, then position, each with the IMU sample
    at the end of the interval). "midpoint": trapezoidal, rates averaged over consecutive samples."""

    # --- PIM: the Pose Inspection Algorithm (Algorithm 1) ---
    pia: bool = True
    """False: every frame after initialisation is FINE and failures never reset the PRM (ablation)."""
    fps: float | None = None
    """Frame rate for THR_2d; None: measured from the interval to the previous frame."""
    area_divisor: float = 100.0
    """THR_area = frame area / area_divisor (paper: 100)."""
    px_error: float = 10.0
    """THR_2d = px_error + px_motion * base_rate / fps (paper: 10, 10, 30)."""
    px_motion: float = 10.0
    base_rate: float = 30.0
    near_m: float = 1e-3
    """A box corner closer than this in front of the camera (or behind it) means TRACKING_LOST."""

    # --- PRM: refinement and the Bias Self-Correction Mechanism ---
    bscm: bool = True
    """False: a backend pose resets orientation and position only; velocity and biases are left alone."""
    backend_after_init: bool = True
    """False: after the first backend pose, no request is ever sent again (IMU only)."""
    pose_gain: float = 1.0
    """Fraction of the way from the propagated pose to the backend pose at the capture time (1.0 = the
    paper: reset to the backend pose). Not in the paper: below 1 it averages a noisy backend's noise."""
    gyro_bias_gain: float = 0.05
    """Fraction of the measured gyro-bias error applied per correction. 1.0 is the paper's formula
    taken literally; with a backend noisy at 0.3 deg it turns every correction into a 0.1 rad/s bias
    jump, so the default averages over ~20 corrections (docs/tracker.md compares the two)."""
    accel_bias_gain: float = 0.05
    """Fraction of the paper's accel-bias estimate V_bias / (t1 - t0) applied per correction."""
    velocity_gain: float = 0.1
    """Fraction of the velocity error at the mid-time removed per correction (1.0 = the paper; a 3 mm
    noisy backend makes V_avg noisy by ~70 mm/s, hence the smaller default)."""
    max_gyro_bias: float = 0.1
    """Clamp on the norm of the gyro bias estimate, rad/s."""
    max_accel_bias: float = 1.0
    """Clamp on the norm of the accelerometer bias estimate, m/s^2."""
    bscm_imu_orientation: bool = True
    """V_avg from the backend's camera-frame translations put into O with the IMU-propagated
    orientation (True), or from the backend's own T_OB positions (False, the paper literally). The
    backend's orientation noise, times the ~1 m object distance, dominates the position of the body
    in O (0.3 deg -> ~6 mm); the propagated orientation is smooth and cancels it to first order."""
    bscm_max_velocity_error: float = 0.5
    """A correction whose V_bias exceeds this (m/s) is an outlier (a wrong backend pose, a glitch):
    the pose is still applied, velocity and biases are left alone."""
    bscm_max_rotation_rate: float = 0.5
    """Likewise for a rotation drift rate |d_theta| / dt above this, rad/s."""
    max_speed_m_s: float = 3.0
    """The velocity set outright from two backend poses after a PRM reset must be below this (m/s; a
    hand-held device moves far slower). A faster V_avg means one of the two poses is wrong: the
    velocity is left alone and the PRM reset again, instead of propagating at that speed."""
    backend_gate_px: float = 0.0
    """0: every backend pose is applied (the paper trusts the backend). Above 0: while the tracker
    is FINE with a known velocity, a backend pose whose 3D-box corners project farther than this on
    average (px) from the propagated pose's at the capture time is GATED (ignored; a new request
    goes out): a vision backend's gross error (a flipped pose) would otherwise be applied."""
    backend_gate_rejects: int = 2
    """This many consecutive gated poses are taken to mean the tracker, not the backend, is wrong:
    the next one is applied whatever it says."""
    gravity_follow: float = 0.0
    """0: gravity in O (g_O) is fixed at initialisation (the paper). k > 0: at each backend correction
    g_O moves a fraction k of the way to where the correction carries it, i.e. towards keeping the
    gravity in the *body* frame (which the IMU measured at initialisation and the gyro has carried
    since) unchanged. With g_O fixed, a backend orientation error d turns into a fake acceleration
    of about 9.81 sin(d) m/s^2 until the next correction (0.3 deg: 0.05 m/s^2; a vision backend's
    5-10 deg: 1-2 m/s^2, metres per second of velocity error within a second); with k near 1 the
    error only tilts the true acceleration. Below 1, g_O stays anchored in the long run against
    gyro drift."""
    bscm_min_interval_s: float = 0.005
    bscm_max_interval_s: float = 1.0
    """BSCM runs only when the backend pose is this far from its reference (short: division by ~0;
    long: the linear drift model no longer holds). A pose closer than the minimum waits: the pose is
    applied but the reference is kept, so V_avg spans at least the minimum baseline (its noise is the
    backend's position noise / baseline; 0.1 s suits a noisy backend at 60-120 FPS)."""

    max_backend_age_s: float = 1.0
    """PIA extension: with the backend in use, a pose whose last backend correction is older than this
    is TRACKING_LOST (IMU-only drift grows without bound: the server is gone or cannot see the object).
    Only with `pia` on and `backend_after_init`; a failure like the paper's two, so it resets the PRM."""

    # --- Initialisation (the paper's "System Initialization") ---
    init_window_s: float = 0.5
    """IMU span before the first backend frame used for gravity and gyro bias."""
    init_require_still: bool = True
    """False: initialise from the window even when the device moves (mean accel taken as gravity)."""
    still_gyro_std: float = 0.02
    """Stillness: RMS deviation of the gyro from its window mean below this, rad/s."""
    still_accel_std: float = 0.1
    """Stillness: RMS deviation of the accelerometer from its window mean below this, m/s^2."""

    # --- Buffers and the state sent with each request ---
    imu_buffer_s: float = 2.0
    """IMU samples (and per-sample states) kept for re-propagation and `pose_at`; responses for
    frames older than this are dropped."""
    state_imu_samples: int = 176
    """Recent IMU samples in `state_bytes()`: 176 makes the blob about 10 kB, as the paper sends."""

    def __post_init__(self) -> None:
        if self.fusion not in FUSIONS:
            raise ValueError(f"fusion must be one of {FUSIONS}, got {self.fusion!r}")
        if not isinstance(self.filter, FilterOptions):
            raise TypeError(f"filter must be FilterOptions, got {type(self.filter).__name__}")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator must be one of {INTEGRATORS}, got {self.integrator!r}")
        if self.fps is not None and not (math.isfinite(self.fps) and self.fps > 0):
            raise ValueError(f"fps must be positive or None, got {self.fps!r}")
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool) or f.name in ("integrator", "fps", "fusion", "filter"):
                continue
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise ValueError(f"{f.name} must be a finite number >= 0, got {value!r}")
        if self.pose_gain > 1 or self.gravity_follow > 1:
            raise ValueError("pose_gain and gravity_follow must be in [0, 1]")
        for name in ("area_divisor", "base_rate", "init_window_s", "imu_buffer_s"):
            if getattr(self, name) <= 0:
                raise ValueError(f"{name} must be > 0")
        if self.bscm_max_interval_s <= self.bscm_min_interval_s:
            raise ValueError("bscm_max_interval_s must exceed bscm_min_interval_s")
        if self.imu_buffer_s <= self.init_window_s:
            raise ValueError("imu_buffer_s must exceed init_window_s")


def preset(name: str) -> TrackerOptions:
    """Named option sets: "filter" (the default for every backend) and "paper" (the paper's PRM with
    BSCM's damped default gains: each backend pose resets the state)."""
    if name == "filter":
        return TrackerOptions()
    if name == "paper":
        return TrackerOptions(fusion="paper")
    raise ValueError(f"unknown tracker preset {name!r}: one of {PRESETS}")
