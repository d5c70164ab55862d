"""IMU synthesis: the exact body rates of a trajectory plus Kalibr's noise model.

gyro  = w_B + b_g + n_g,      accel = R_WB^T (a_W - g_W) + b_a + n_a
n ~ N(0, (density * sqrt(rate))^2) per sample (white noise, discretised as Kalibr defines it);
b starts at a random turn-on value and walks: b_{k+1} = b_k + random_walk * sqrt(dt_k) * N(0, 1).

Profiles:
- pixel2: the paper's LSM6DSM densities (gyro 6.63e-5 rad/s/sqrt(Hz), accel 7.35e-4 m/s^2/sqrt(Hz)).
  The paper gives no bias figures; we choose, for a phone whose OS has calibrated its sensors
  (Android's calibrated gyroscope / accelerometer streams), a turn-on bias of 3e-3 rad/s
  (0.17 deg/s; the raw LSM6DSM zero-rate level is +-3 deg/s before calibration) and 0.05 m/s^2
  (5 mg; raw zero-g level +-40 mg) per axis (1 sigma), and random walks of 4e-5 rad/s^2/sqrt(Hz)
  and 1e-3 m/s^3/sqrt(Hz): about twice the ADIS16448's (EuRoC) for the gyro, a third of EuRoC's
  inflated accel figure, and in the range Allan analyses of phone IMUs report.
- euroc: the ADIS16448 of EuRoC (the shared imu0_sensor.yaml values), turn-on biases of the size
  EuRoC's ground truth estimates for V1_02 (0.03 rad/s, 0.08 m/s^2).
- ideal: no noise, no bias.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from flextrack.formats.euroc import ImuData
from flextrack.formats.kalibr import ImuNoise
from flextrack.simulator.kinematics import Kinematics


@dataclass(frozen=True)
class ImuProfile:
    name: str
    noise: ImuNoise  # continuous densities; update_rate is set per sequence
    gyro_bias_sigma: float  # rad/s, turn-on bias per axis
    accel_bias_sigma: float  # m/s^2
    comment: str


PROFILES = {
    "pixel2": ImuProfile("pixel2", ImuNoise(6.63e-5, 4.0e-5, 7.35e-4, 1.0e-3, 200.0), 3e-3, 0.05,
                         "LSM6DSM (Google Pixel 2): paper's densities; flextrack's chosen bias figures"),
    "euroc": ImuProfile("euroc", ImuNoise(1.6968e-4, 1.9393e-5, 2.0e-3, 3.0e-3, 200.0), 0.03, 0.08,
                        "ADIS16448 (EuRoC VI-Sensor imu0_sensor.yaml)"),
    "ideal": ImuProfile("ideal", ImuNoise(0.0, 0.0, 0.0, 0.0, 200.0), 0.0, 0.0, "noise-free, bias-free"),
}


def profile(name: str, rate_hz: float) -> ImuProfile:
    if name not in PROFILES:
        raise ValueError(f"unknown IMU profile {name!r}; choose one of {sorted(PROFILES)}")
    if not rate_hz > 0:
        raise ValueError("the IMU rate must be positive")
    p = PROFILES[name]
    return replace(p, noise=replace(p.noise, update_rate=float(rate_hz)))


@dataclass
class ImuRecord:
    imu: ImuData
    bias_gyro: np.ndarray  # (N, 3) the biases actually added
    bias_accel: np.ndarray  # (N, 3)


def sample_times(start_s: float, end_s: float, rate_hz: float, jitter_s: float = 0.0,
                 rng: np.random.Generator | None = None) -> np.ndarray:
    """Sample instants (s) at `rate_hz`; with jitter each moves by N(0, jitter_s), kept in order."""
    n = int(np.floor((end_s - start_s) * rate_hz + 1e-9)) + 1
    t = start_s + np.arange(n) / rate_hz
    if jitter_s > 0:
        dt = 1.0 / rate_hz
        t = t + np.clip(rng.normal(0.0, jitter_s, size=n), -0.4 * dt, 0.4 * dt)
        t[0] = start_s
    return t


def synthesize(t_s: np.ndarray, body: Kinematics, prof: ImuProfile, rng: np.random.Generator) -> ImuRecord:
    """IMU samples at times t_s (s) of a body with exact kinematics `body` (evaluated at t_s)."""
    n = len(t_s)
    noise = prof.noise
    dt = np.diff(t_s, prepend=t_s[0])
    bias_g = _bias(rng, n, prof.gyro_bias_sigma, noise.gyroscope_random_walk, dt)
    bias_a = _bias(rng, n, prof.accel_bias_sigma, noise.accelerometer_random_walk, dt)
    sigma_g = noise.gyroscope_noise_density * np.sqrt(noise.update_rate)
    sigma_a = noise.accelerometer_noise_density * np.sqrt(noise.update_rate)
    gyro = body.w_X + bias_g + sigma_g * rng.standard_normal((n, 3))
    accel = body.specific_force() + bias_a + sigma_a * rng.standard_normal((n, 3))
    t_ns = np.round(np.asarray(t_s) * 1e9).astype(np.int64)
    return ImuRecord(ImuData(t_ns, gyro, accel), bias_g, bias_a)


def _bias(rng: np.random.Generator, n: int, turn_on_sigma: float, random_walk: float, dt: np.ndarray) -> np.ndarray:
    start = turn_on_sigma * rng.standard_normal(3)
    steps = random_walk * np.sqrt(dt)[:, None] * rng.standard_normal((n, 3))
    return start + np.cumsum(steps, axis=0)
