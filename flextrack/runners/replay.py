"""Replay a sequence through the tracker in virtual time: fast, and bit-identical for one seed.

One event queue (heapq) holds the IMU samples, the frames and the backend responses, ordered by
virtual time; at equal times IMU first, then responses, then frames. A frame reaches the tracker the
sequence's frame latency after its capture time (`exchange.frame_latency_ns`: a phone's camera pipeline;
the simulator's frames none), stamped with its capture time. Nothing is measured:

- a frame's request leaves after the (stretched, modelled) PIM cost;
- it reaches the backend after the uplink delay, the backend takes its modelled compute time, the
  answer comes back after the downlink delay (both legs from the seeded network model, stamped by
  the interceptor when the backend is a real gRPC server), and the correction lands after the
  (stretched, modelled) PRM cost.

The backend's real answer is fetched at once (it is a pure function of the request), so the wall
time of a 30 s sequence is the tracker's own compute time plus one loopback round trip a request.
"""

from __future__ import annotations

import heapq
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from client_sdk import TrackerOptions
from client_sdk.crop import CropOptions, request_crop
from client_sdk.network_model import NetworkOptions
from client_sdk.slowdown import PIXEL2_FACTOR, FrontendCosts, Slowdown
from flextrack.formats.sequence import Sequence
from flextrack.geometry.camera import bbox_corners
from flextrack.runners.exchange import apply_answer, finish, frame_latency_ns, frame_request, tracker_for
from flextrack.runners.live import Progress
from flextrack.runners.payload import stand_in_jpeg
from flextrack.runners.results import TrackRecord

_IMU, _RESPONSE, _FRAME = 0, 1, 2


@dataclass(frozen=True)
class ReplayOptions:
    network: NetworkOptions = field(default_factory=NetworkOptions)
    slowdown: float = PIXEL2_FACTOR
    costs: FrontendCosts = field(default_factory=FrontendCosts)
    backend_compute_ms: float = 0.0  # the paper: "the backend task started instantly" (oracles)
    estimator: str = "gt"  # registry name on the server
    session_id: str = "replay"
    record_error_dynamics: bool = True  # the filter's, for the NEES interval (off: timing the tracker alone)
    crop: CropOptions = field(default_factory=CropOptions)  # with rendered frames: what part of a frame to send


def replay(seq: Sequence, backend, vertices_O: np.ndarray, tracker_options: TrackerOptions | None = None,
           options: ReplayOptions = ReplayOptions(), wrap: Callable | None = None,
           frame_jpeg: Callable[[int], bytes] | None = None,
           progress: Callable[[Progress], None] | None = None) -> TrackRecord:
    """Track `seq` with `backend` (see flextrack.runners.backends) and record every frame against ground truth.

    `wrap` may put a proxy around the tracker (the timing experiment measures its calls that way);
    `frame_jpeg(frame_id, crop)` gives the image a request carries, the frame or the crop `options.crop` chose
    (default: the 90 kB stand-in, always whole); `progress` is called after every frame (it decides itself how
    often to show anything).
    """
    tracker = tracker_for(seq, vertices_O, tracker_options, options.record_error_dynamics)
    if wrap is not None:
        tracker = wrap(tracker)
    slowdown = Slowdown(options.slowdown, options.costs)
    record = TrackRecord(seq.camera, vertices_O)
    image = stand_in_jpeg(seq.camera.width, seq.camera.height)
    corners_O = bbox_corners(vertices_O)
    compute_ns = round(options.backend_compute_ms * 1e6)

    events: list[tuple] = []  # (t_ns, kind, n, payload)
    imu = seq.imu
    for i, t in enumerate(imu.t_ns):
        events.append((int(t), _IMU, i, None))
    latency = frame_latency_ns(seq)
    for i, (fid, t) in enumerate(zip(seq.frame_ids, seq.frame_times_ns)):
        events.append((int(t) + latency, _FRAME, i, int(fid)))
    heapq.heapify(events)
    n = len(events)
    t_first, t_last = (int(seq.frame_times_ns[0]), int(seq.frame_times_ns[-1])) if len(seq.frame_times_ns) else (0, 0)

    while events:
        t_ns, kind, i, payload = heapq.heappop(events)
        if kind == _IMU:
            tracker.add_imu(t_ns, imu.gyro[i], imu.accel[i])
        elif kind == _FRAME:  # t_ns: when it reaches the tracker; the frame is stamped with its capture time
            captured = int(seq.frame_times_ns[i])
            result = tracker.add_frame(captured)
            record.add(payload, captured, result.status.name, result.T_CO, seq.gt_T_CO.get(payload), result.covariance)
            if progress is not None:
                progress(Progress((captured - t_first) * 1e-9, (t_last - t_first) * 1e-9, record, result.status.name,
                                  True))
            if result.request is not None:
                crop = None if frame_jpeg is None else request_crop(tracker, result.request, corners_O, options.crop)
                request = frame_request(seq, tracker, payload, result.request.frame_t_ns,
                                        image if frame_jpeg is None else frame_jpeg(payload, crop),
                                        session_id=options.session_id, estimator=options.estimator,
                                        client_state=tracker.state_bytes(), crop=crop)
                record.requests += 1
                record.request_bytes.append(request.ByteSize())
                response, delays = backend.call(request)
                arrive = (t_ns + slowdown.virtual_ns("pim") + delays.uplink_ns + compute_ns + delays.downlink_ns
                          + slowdown.virtual_ns("prm"))
                heapq.heappush(events, (arrive, _RESPONSE, n, (result.request, response)))
                n += 1
        else:
            request, response = payload
            apply_answer(tracker, request.request_id, response, record)
    return finish(tracker, record)
