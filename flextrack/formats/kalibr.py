"""Kalibr / EuRoC sensor.yaml files: IMU noise model and camera calibration."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml


@dataclass
class ImuNoise:
    """Continuous-time densities as Kalibr defines them; discrete sigma = density * sqrt(rate)."""

    gyroscope_noise_density: float  # rad/s/sqrt(Hz)
    gyroscope_random_walk: float  # rad/s^2/sqrt(Hz)
    accelerometer_noise_density: float  # m/s^2/sqrt(Hz)
    accelerometer_random_walk: float  # m/s^3/sqrt(Hz)
    update_rate: float  # Hz


def _matrix(node) -> np.ndarray:
    """A 4x4 from EuRoC's `{rows, cols, data}` or a plain nested list."""
    if isinstance(node, dict):
        return np.asarray(node["data"], dtype=float).reshape(node["rows"], node["cols"])
    return np.asarray(node, dtype=float)


def _load_yaml(path: str | Path) -> dict:
    """EuRoC files start with OpenCV's `%YAML:1.0` line, which is not valid YAML: drop it."""
    text = "\n".join(line for line in Path(path).read_text().splitlines() if not line.startswith("%YAML"))
    return yaml.safe_load(text)


def read_imu_sensor(path: str | Path) -> tuple[ImuNoise, np.ndarray]:
    """(noise model, T_BS) of an IMU sensor.yaml; T_BS is identity when absent."""
    doc = _load_yaml(path)
    noise = ImuNoise(
        float(doc["gyroscope_noise_density"]),
        float(doc["gyroscope_random_walk"]),
        float(doc["accelerometer_noise_density"]),
        float(doc["accelerometer_random_walk"]),
        float(doc.get("update_rate", doc.get("rate_hz", 200.0))),
    )
    T_BS = _matrix(doc["T_BS"]) if "T_BS" in doc else np.eye(4)
    return noise, T_BS


def write_imu_sensor(path: str | Path, noise: ImuNoise, T_BS: np.ndarray, comment: str = "") -> None:
    doc = {
        "sensor_type": "imu",
        "comment": comment,
        "T_BS": {"cols": 4, "rows": 4, "data": [float(x) for x in np.asarray(T_BS).ravel()]},
        "rate_hz": float(noise.update_rate),
        "update_rate": float(noise.update_rate),
        "gyroscope_noise_density": noise.gyroscope_noise_density,
        "gyroscope_random_walk": noise.gyroscope_random_walk,
        "accelerometer_noise_density": noise.accelerometer_noise_density,
        "accelerometer_random_walk": noise.accelerometer_random_walk,
    }
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(yaml.safe_dump(doc, sort_keys=False))


@dataclass
class CameraCalibration:
    K: np.ndarray  # 3x3
    width: int
    height: int
    distortion: np.ndarray  # OpenCV order k1 k2 p1 p2
    T_BS: np.ndarray  # camera -> body
    rate_hz: float


def read_camera_sensor(path: str | Path) -> CameraCalibration:
    doc = _load_yaml(path)
    fu, fv, cu, cv = (float(x) for x in doc["intrinsics"])
    w, h = (int(x) for x in doc["resolution"])
    K = np.array([[fu, 0, cu], [0, fv, cv], [0, 0, 1.0]])
    return CameraCalibration(
        K, w, h, np.asarray(doc.get("distortion_coefficients", []), dtype=float),
        _matrix(doc["T_BS"]), float(doc.get("rate_hz", 20.0)),
    )
