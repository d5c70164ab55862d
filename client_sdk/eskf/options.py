"""The error-state Kalman filter's options: noise models and initial uncertainties, nothing tuned per backend.

IMU densities are Kalibr's (continuous time); the runners fill them from the sequence's
`imu0/sensor.yaml`. The defaults are the Pixel 2's (LSM6DSM) densities from the paper and the
simulator's chosen random walks. docs/tracker.md gives the equations these enter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields


@dataclass
class FilterOptions:
    """The error-state filter's settings (`TrackerOptions.filter`): the IMU's noise, the initial
    uncertainty, the time offset, how backend answers are weighed and gated, and what a frame shows.
    The runners fill the IMU densities from the sequence's Kalibr `imu0/sensor.yaml`."""

    # --- IMU noise (Kalibr imu0/sensor.yaml) ---
    gyroscope_noise_density: float = 6.63e-5
    """rad/s/sqrt(Hz)."""
    gyroscope_random_walk: float = 4.0e-5
    """rad/s^2/sqrt(Hz)."""
    accelerometer_noise_density: float = 7.35e-4
    """m/s^2/sqrt(Hz)."""
    accelerometer_random_walk: float = 1.0e-3
    """m/s^3/sqrt(Hz)."""
    noise_inflation: float = 1.0
    """Multiplies the IMU densities above (> 1 when a yaml's lab figures understate the sensor in use)."""
    adapt_imu_noise: bool = True
    """Raise the white-noise densities to what the IMU shows in use (the second differences of the means of
    consecutive samples, which the midpoint integrator uses, over the last `noise_window_samples`), never
    lower them: a yaml's lab figures and a vibrating device differ by an order of magnitude (EuRoC's drone)."""
    noise_window_samples: int = 200
    """The running estimate's memory, samples (1 s at 200 Hz)."""
    match_imu_noise: bool = True
    """Raise the densities further to what the answers' innovations show (covariance matching,
    `eskf.noise_matching`): a phone's scale and misalignment errors, filtered stream and irregular stamps
    look like far more white noise than its samples show (a hand-held Nexus 5: ~50x the yaml's gyro)."""
    noise_match_answers: float = 100.0
    """The innovation fit's memory, answers (~6 s at the phone experiment's answer rate)."""
    gyroscope_scale_error: float = 0.02
    """1-sigma of each entry of the gyro's scale-and-misalignment error (a fraction): the rate it reports is
    (I + M) times the true one. A consumer MEMS gyro's datasheet allows +-3 % sensitivity and +-2 % cross-axis
    (InvenSense MPU-6500); nothing calibrates it on a phone. Its error, M w, grows with the rate, which no
    white density models (`eskf.propagator`); a sequence whose IMU has none (the simulator's) declares 0
    (sequence.yaml `gyroscope_scale_error`)."""

    max_imu_gap_s: float = 0.05
    """An interval between IMU samples longer than this (or a time this far past the newest sample) was not
    measured: a phone's stream stops for seconds at times. The state then goes on at the angular rate and
    velocity the answers show (a constant-velocity model, `eskf.coasting`), its covariance growing at the
    hand-motion densities below, so that the answers alone keep the pose on track, and FINE as far as they
    keep it certain."""
    gap_angular_accel_density: float = 3.0
    """rad/s^2/sqrt(Hz): a hand's unmeasured angular acceleration (~1 rad/s changing within ~0.3 s), the
    motion model's guess until the answers show (`match_gap_noise`)."""
    gap_accel_density: float = 2.0
    """m/s^2/sqrt(Hz): its unmeasured linear acceleration, likewise."""
    gap_rate_std: float = 1.0
    """rad/s, per axis: the angular rate's uncertainty when a gap starts with no recent gyro sample (a start
    inside a gap)."""
    match_gap_noise: bool = True
    """Fit the two hand-motion densities to the answers' innovations across gaps (covariance matching, the
    fit itself: over `noise_match_answers` answers), so that the pose's uncertainty is what the hand's
    motion makes it."""

    # --- Initial uncertainty (1 sigma, per axis) ---
    init_velocity_std: float = 0.3
    """m/s: the device may be moving when tracking starts; the first answers pin the velocity down."""
    init_gyro_bias_std: float = 0.02
    """rad/s: a moving start cannot measure the gyro bias (a still one measures it, see below)."""
    init_accel_bias_std: float = 0.1
    """m/s^2: twice the calibrated turn-on bias of a phone's accelerometer stream (the simulator's
    Pixel 2: 0.05; EuRoC's ADIS16448: ~0.08); a still window cannot tell it from gravity (the two
    start correlated)."""
    init_gravity_std: float = 0.3
    """m/s^2, per axis of g_O, when gravity comes from a moving device's IMU window (~1.8 deg)."""
    still_gravity_std: float = 0.003
    """m/s^2, the least uncertainty of gravity from a still window; above it, the standard error of the
    window's mean specific force (`initialization.InitEstimate`), beside the errors gravity shares with
    the first pose's orientation and the accelerometer bias (modelled as correlations). An over-cautious
    start lets the first noisy answers pull gravity and the gyro bias off (`flextrack experiment filter
    --seeds 3`, circular medium: 1.14 px at 84fe2b1 with a fixed 0.03 m/s^2 and 1 mrad/s, 1.10 px at
    c9ddc64 with the standard errors and the ease below)."""
    still_gyro_bias_std: float = 1e-4
    """rad/s, the least uncertainty of the gyro bias from a still window; above it, the standard error of
    the window's mean gyro."""
    gravity_state: bool = True
    """False: g_O fixed at initialisation (the ablation "no gravity state")."""

    # --- Camera-IMU time offset (t_imu = t_camera + offset) ---
    time_offset_s: float = 0.0
    """Initial value, s."""
    time_offset_std_s: float = 0.02
    """Initial uncertainty, s; 0 switches the online estimation off."""

    # --- Backend answers ---
    use_backend_covariance: bool = True
    """False: every answer gets the default below, whatever the backend says (ablation)."""
    default_rotation_std_deg: float = 1.0
    """Per axis, for answers that come without a covariance (documented default)."""
    default_translation_std_m: float = 0.01
    """Per axis, likewise."""
    answer_floor_rotation_deg: float = 0.1
    """Per axis: an answer's variance is raised to at least this (and the next) on its diagonal. However exact
    a backend's pose of the camera, the tracker turns it into the IMU's with an extrinsic known to ~0.1 deg
    and ~1 mm and a frame time known to ~1 ms (a phone's rolling shutter and stamps); a ground-truth
    backend's micrometres taken at their word had every later answer gated on real IMU (4.85 px against
    the noisy backend's 3.4). 0 turns the floor off. This is a real device's default: flextrack's runners set
    the floor from what a sequence declares it cannot know (sequence.yaml `timing_extrinsic_std`; the
    simulator's extrinsic and frame times are exact, 0) and keep this where it declares nothing."""
    answer_floor_translation_m: float = 0.001
    """Per axis, likewise (m)."""
    gate_chi2: float = 22.46
    """An answer whose innovation's Mahalanobis distance squared exceeds this is rejected (chi-square,
    6 dof, 99.9 %)."""
    max_rejections: int = 3
    """This many rejected answers in a row mean the filter, not the backend, is wrong: re-initialise
    from the last of them."""

    # --- What a frame shows ---
    ease_s: float = 0.02
    """Time constant (s) over which a correction's jump of the shown pose is eased in (0: at once), and
    at least `ease_min_frames` frame intervals. The filter's state takes each answer at once; only the
    pose a frame reports glides, trading a little accuracy for less visible shake (with these defaults,
    jitter 0.17 px on the peer cells of `flextrack experiment filter`)."""
    ease_min_frames: float = 1.5

    # --- Evaluation ---
    record_error_dynamics: bool = False
    """Keep the linearised error dynamics (`eskf.error_dynamics`), from which the evaluation derives the interval
    of a run's mean NEES; one 19x19 product more per IMU sample. The runners switch it on."""

    # --- Status from the covariance ---
    max_sigma_px: float = 6.0
    """A pose whose 1-sigma uncertainty, projected on the object's box corners (RMS, px), exceeds
    this is not FINE, whatever the PIA says (3 sigma ~ 20 px)."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool):
                continue
            if f.name == "time_offset_s":
                ok = isinstance(value, (int, float)) and math.isfinite(value) and abs(value) < 1.0
            else:
                ok = isinstance(value, (int, float)) and math.isfinite(value) and value >= 0
            if not ok:
                raise ValueError(f"filter option {f.name} must be a finite number >= 0 (|offset| < 1 s), "
                                 f"got {value!r}")
        for name in ("default_rotation_std_deg", "default_translation_std_m", "gate_chi2", "max_sigma_px",
                     "noise_inflation"):
            if getattr(self, name) <= 0:
                raise ValueError(f"filter option {name} must be > 0")
        if self.noise_window_samples < 1:
            raise ValueError("filter option noise_window_samples must be >= 1")
        if self.max_rejections < 1:
            raise ValueError("filter option max_rejections must be >= 1")
