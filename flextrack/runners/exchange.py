"""What both runners (replay and live) do the same way: build the tracker for a sequence, build a
frame's request, and hand the backend's answer to the tracker.

One home, so that the two shells cannot drift apart: the prior on every request after
initialisation, the IMU noise from the sequence's Kalibr yaml, the answer floor from what the sequence
declares it cannot know, the answer's covariance decoded once (a bad one is counted and replaced by the
tracker's documented default).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from client_sdk import TrackerOptions, create_tracker
from client_sdk.transport import make_request, prior_of
from flextrack import wire
from flextrack.formats.sequence import Sequence
from flextrack.geometry.camera import bbox_corners
from flextrack.runners.results import TrackRecord
from flextrack.v1 import pose_estimation_pb2 as pb

# sequence.yaml's key for what a recording cannot know exactly: its camera-IMU extrinsic and its frame times,
# as one per-axis rotation (deg) and translation (m) on every answer (FilterOptions.answer_floor_*).
TIMING_EXTRINSIC_KEY = "timing_extrinsic_std"
# ... and for its gyro's scale-and-misalignment error, a fraction per entry (FilterOptions.gyroscope_scale_error).
GYRO_SCALE_KEY = "gyroscope_scale_error"
# ... and for how long after its capture a frame reaches the tracker (ms): a phone's camera pipeline (exposure,
# readout, the ISP) hands the app a frame tens of ms after its timestamp, by when the IMU samples that cover the
# frame's time have arrived (an IMU clock ahead of the camera's by ~16 ms on the Nexus 5 recordings, 40 ms on
# another phone, then needs no extrapolation past the newest sample: docs/own-data.md).
FRAME_LATENCY_KEY = "frame_latency_ms"
DEFAULT_FRAME_LATENCY_MS = 50.0  # a recording that declares nothing: the low end of a phone's 50-100 ms
# What the simulator declares (flextrack.simulator.generate writes it): its extrinsic, frame times and gyro are
# exact, and its frames reach the tracker at their capture time (the paper's experiments).
SIMULATOR_DECLARATIONS = {TIMING_EXTRINSIC_KEY: {"rotation_deg": 0.0, "translation_m": 0.0}, GYRO_SCALE_KEY: 0.0,
                          FRAME_LATENCY_KEY: 0.0}
# The filter option each declaration sets (`declared_filter_options`).
DECLARED_BY = {"answer_floor_rotation_deg": TIMING_EXTRINSIC_KEY, "answer_floor_translation_m": TIMING_EXTRINSIC_KEY,
               "gyroscope_scale_error": GYRO_SCALE_KEY}


def declared_floor(seq: Sequence) -> tuple[float, float] | None:
    """(rotation deg, translation m) the sequence declares under TIMING_EXTRINSIC_KEY (the simulator: 0, its
    extrinsic and frame times are exact), or None when it declares nothing (a real recording: the tracker's
    default floor). ValueError for a declaration that is not two finite numbers >= 0."""
    declared = seq.meta.get(TIMING_EXTRINSIC_KEY)
    if declared is None:
        return None
    where = f"{seq.root / 'sequence.yaml'}: {TIMING_EXTRINSIC_KEY}"
    if not isinstance(declared, dict):
        raise ValueError(f"{where} must map rotation_deg and translation_m to numbers, got {declared!r}")  # noqa: TRY004 (a file, not an argument)
    try:
        values = (float(declared["rotation_deg"]), float(declared["translation_m"]))
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{where} must map rotation_deg and translation_m to numbers, got {declared!r}") from None
    if not all(math.isfinite(v) and v >= 0 for v in values):
        raise ValueError(f"{where}: rotation_deg and translation_m must be finite and >= 0, got {declared!r}")
    return values


def declared_gyro_scale(seq: Sequence) -> float | None:
    """The gyro scale-and-misalignment error the sequence declares under GYRO_SCALE_KEY (the simulator: 0, its
    gyro has none), or None when it declares nothing (a real recording: the tracker's default, a phone's).
    ValueError for a declaration that is not a number in [0, 0.5)."""
    return _declared_number(seq, GYRO_SCALE_KEY, 0.5, "a fraction")


def frame_latency_ns(seq: Sequence) -> int:
    """How long after its capture time a frame of `seq` reaches the tracker, ns: what the sequence declares under
    FRAME_LATENCY_KEY (the simulator: 0), else DEFAULT_FRAME_LATENCY_MS (a real recording: a phone's camera
    pipeline). ValueError for a declaration that is not a number of ms in [0, 1000)."""
    declared = _declared_number(seq, FRAME_LATENCY_KEY, 1000.0, "a number of ms")
    return round((DEFAULT_FRAME_LATENCY_MS if declared is None else declared) * 1e6)


def _declared_number(seq: Sequence, key: str, below: float, what: str) -> float | None:
    """sequence.yaml's number under `key`, None when absent; ValueError unless it lies in [0, below)."""
    declared = seq.meta.get(key)
    if declared is None:
        return None
    try:
        value = float(declared)
    except (TypeError, ValueError):
        value = math.nan
    if not 0.0 <= value < below:
        raise ValueError(f"{seq.root / 'sequence.yaml'}: {key} must be {what} in [0, {below:g}), got {declared!r}")
    return value


def declared_filter_options(seq: Sequence) -> dict[str, float]:
    """The filter options the sequence's declarations set (`DECLARED_BY`), by name; none for what it leaves
    undeclared (the tracker's defaults, a real recording's). ValueError for a malformed declaration."""
    out: dict[str, float] = {}
    floor = declared_floor(seq)
    if floor is not None:
        out["answer_floor_rotation_deg"], out["answer_floor_translation_m"] = floor
    scale = declared_gyro_scale(seq)
    if scale is not None:
        out["gyroscope_scale_error"] = scale
    return out


def tracker_for(seq: Sequence, vertices_O: np.ndarray, options: TrackerOptions | None,
                record_error_dynamics: bool = True):
    """The tracker core the options name; the filter's IMU densities are the sequence's (imu0/sensor.yaml), so is
    what the sequence declares (`declared_filter_options`), and it keeps its error dynamics for the NEES interval
    unless told not to (the timing experiment)."""
    options = options or TrackerOptions()
    if options.fusion == "filter":
        n = seq.imu_noise
        fo = replace(
            options.filter, gyroscope_noise_density=n.gyroscope_noise_density,
            gyroscope_random_walk=n.gyroscope_random_walk, accelerometer_noise_density=n.accelerometer_noise_density,
            accelerometer_random_walk=n.accelerometer_random_walk, record_error_dynamics=record_error_dynamics,
            **declared_filter_options(seq))
        options = replace(options, filter=fo)
    return create_tracker(options, seq.camera, seq.T_BC, bbox_corners(vertices_O))


def frame_request(seq: Sequence, tracker, frame_id: int, capture_time_ns: int, image: bytes, *, session_id: str,
                  estimator: str, client_state: bytes, crop: pb.Crop | None = None) -> pb.EstimateRequest:
    """The request for one frame (`image`: its JPEG, or the JPEG of `crop`'s rectangle of it), with the tracker's
    prior at the capture time once it has one."""
    width, height = (crop.width, crop.height) if crop is not None else (seq.camera.width, seq.camera.height)
    return make_request(
        frame_id=frame_id, capture_time_ns=capture_time_ns, session_id=session_id, estimator=estimator,
        object_id=seq.object_id, sequence=seq.name, image=image, width=width, height=height,
        intrinsics=wire.intrinsics_to_pb(seq.camera), client_state=client_state,
        prior=prior_of(tracker, capture_time_ns), crop=crop)


def apply_answer(tracker, request_id: int, response: pb.EstimateResponse, record: TrackRecord) -> None:
    """Hand one backend answer to the tracker and count it in the record."""
    if response.status != pb.EstimateResponse.OK:
        record.failures += 1
        if not record.first_refusal:
            record.first_refusal = f"{pb.EstimateResponse.Status.Name(response.status)}: {response.message}"
        tracker.on_backend_response(request_id, response.capture_time_ns, None, False)
        return
    record.responses += 1
    try:
        covariance = wire.covariance_from_pb(response.pose_covariance, "the backend's covariance")
    except wire.BadCovariance:
        covariance = None
        record.bad_covariances += 1
    tracker.on_backend_response(request_id, response.capture_time_ns, wire.pose_from_pb(response.pose), True,
                                covariance)


def finish(tracker, record: TrackRecord) -> TrackRecord:
    """What the tracker learned that the record reports: the filter's camera-IMU time offset and error dynamics."""
    offset = getattr(tracker, "time_offset_s", None)
    if offset is not None:
        record.time_offset_ms = offset * 1e3
        record.time_offset_sigma_ms = getattr(tracker, "time_offset_std_s", math.nan) * 1e3
    record.error_dynamics = getattr(tracker, "error_dynamics", None)
    return record
