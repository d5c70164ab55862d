"""The paper's "GT" and "Noisy" backends: answer from a sequence folder's ground truth.

The pose at a request's capture time is interpolated between the ground-truth samples around it
(linear in translation, slerp in rotation). Optional Gaussian noise per axis is drawn from a
generator seeded by (seed, sequence, object, capture time), so a replay gets bit-identical answers
whatever order or thread its requests arrive in.

Every pose carries its covariance in the wire convention (flextrack.wire): the noise is drawn as
R = Exp(dr) R_true, t = t_true + dt with dr ~ N(0, noise_r^2 I), dt ~ N(0, noise_t^2 I), so the
error e = (-dr, -dt) has covariance diag(noise_r^2 x3, noise_t^2 x3) exactly. A floor is added in
quadrature: at a frame's own time the ground truth is the pose, and the floor (`floor_r_deg`,
`floor_t_m`, default 1e-6 deg and 10 nm per axis) only keeps the matrix positive definite; between
frames the pose is interpolated, a few micrometres off on fast motion, and `INTERPOLATED_R_DEG`,
`INTERPOLATED_T_M` (1e-4 deg, 2 um) are added too. It claims no more than that: how closely a tracker can
use such answers is the tracker's business (the filter's update allows for the time offset's products
with the rates it multiplies, which is what precise answers need, `client_sdk.eskf.pose_update`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from estimators.base import EstimateInput, EstimateOutput, Estimator, Status, UnknownSequence
from flextrack import wire
from flextrack.formats import sequence as sequence_io
from flextrack.geometry import se3, so3
from flextrack.geometry.camera import PinholeCamera


@dataclass(frozen=True)
class _GroundTruth:
    object_id: str
    frame_times_ns: np.ndarray  # (F,) sorted, every frame of the table
    poses: np.ndarray  # (F, 4, 4) T_CO; NaN where the frame has no ground truth
    has_gt: list[bool]  # (F,) a plain list: indexing it per request is cheaper than numpy
    camera: PinholeCamera


def _ground_truth(source: Path | sequence_io.Sequence) -> _GroundTruth:
    seq = source if isinstance(source, sequence_io.Sequence) else sequence_io.load(source)
    poses = np.full((len(seq.frame_ids), 4, 4), np.nan)
    for i, frame_id in enumerate(seq.frame_ids):
        if int(frame_id) in seq.gt_T_CO:
            poses[i] = seq.gt_T_CO[int(frame_id)]
    return _GroundTruth(seq.object_id, seq.frame_times_ns, poses, (~np.isnan(poses[:, 0, 0])).tolist(), seq.camera)


def sequence_folders(root: str | Path) -> list[Path]:
    """`root` itself when it holds rig.yaml, else its subfolders that do."""
    root = Path(root)
    if (root / "rig.yaml").is_file():
        return [root]
    if not root.is_dir():
        raise FileNotFoundError(f"sequence root {root} does not exist")
    return sorted(p for p in root.iterdir() if (p / "rig.yaml").is_file())

FLOOR_R_DEG, FLOOR_T_M = 1e-6, 1e-8  # per axis, in quadrature (module doc)
INTERPOLATED_R_DEG, INTERPOLATED_T_M = 1e-4, 2e-6  # per axis, in quadrature too, between frames


class GtOracleEstimator(Estimator):
    kind = "gt_oracle"
    version = "1.0"
    cheap = True  # a table look-up and an interpolation: tens of microseconds
    description = "ground truth of a sequence folder at the capture time, with optional seeded Gaussian noise"

    def __init__(self, name: str = "gt_oracle", sequence_roots=(), noise_t_m: float = 0.0,
                 noise_r_deg: float = 0.0, seed: int = 0, floor_r_deg: float = FLOOR_R_DEG,
                 floor_t_m: float = FLOOR_T_M):
        super().__init__(name)
        if noise_t_m < 0 or noise_r_deg < 0:
            raise ValueError(f"estimator '{name}': noise_t_m and noise_r_deg must be >= 0")
        if not (floor_r_deg > 0 and floor_t_m > 0):
            raise ValueError(f"estimator '{name}': floor_r_deg and floor_t_m must be > 0 (the covariance must be "
                             f"positive definite)")
        self.noise_t_m = float(noise_t_m)
        self.noise_r_rad = float(np.radians(noise_r_deg))
        self.seed = int(seed)
        # one matrix at frames and one between them (built once: this runs per request on the event loop)
        self.covariance = wire.diagonal_covariance(float(np.hypot(self.noise_r_rad, np.radians(floor_r_deg))),
                                                   float(np.hypot(self.noise_t_m, floor_t_m)))
        self.covariance_interpolated = self.covariance + wire.diagonal_covariance(np.radians(INTERPOLATED_R_DEG),
                                                                                  INTERPOLATED_T_M)
        for matrix in (self.covariance, self.covariance_interpolated):
            matrix.setflags(write=False)
        self._sequences: dict[str, _GroundTruth] = {}
        for root in sequence_roots:
            for folder in sequence_folders(root):
                self.add_sequence(folder)

    @classmethod
    def from_spec(cls, spec) -> GtOracleEstimator:
        spec.check_params({"sequence_roots", "noise_t_m", "noise_r_deg", "seed", "floor_r_deg", "floor_t_m"})
        p = spec.params
        return cls(spec.name, [spec.path(r) for r in p.get("sequence_roots", [])], p.get("noise_t_m", 0.0),
                   p.get("noise_r_deg", 0.0), p.get("seed", 0), p.get("floor_r_deg", FLOOR_R_DEG),
                   p.get("floor_t_m", FLOOR_T_M))

    def add_sequence(self, path: str | Path | sequence_io.Sequence, name: str | None = None) -> str:
        """Load (or reload) a sequence folder, or take one a runner already loaded (with its whole ground truth,
        so that a run parses its folder once); requests name it by `name`, default the folder's name."""
        source = path if isinstance(path, sequence_io.Sequence) else Path(path)
        name = name or source.name
        self._sequences[name] = _ground_truth(source)
        return name

    @property
    def sequences(self) -> list[str]:
        return sorted(self._sequences)

    @property
    def objects(self) -> list[str]:
        return sorted({gt.object_id for gt in self._sequences.values()})

    def _sequence(self, name: str) -> tuple[str, _GroundTruth]:
        if not name and len(self._sequences) == 1:
            name = next(iter(self._sequences))
        if name not in self._sequences:
            raise UnknownSequence(f"estimator '{self.name}' has no sequence '{name}'; loaded: {self.sequences}")
        return name, self._sequences[name]

    def _pose_at(self, gt: _GroundTruth, t_ns: int) -> tuple[np.ndarray | None, bool]:
        """(T_CO, at a frame's own time): None outside the table or next to a frame without ground truth."""
        times, has_gt = gt.frame_times_ns, gt.has_gt
        i = int(np.searchsorted(times, t_ns, side="right")) - 1
        if i < 0 or t_ns > times[-1]:
            return None, False
        if times[i] == t_ns:  # a frame's own time: the common case in replays, kept cheap
            return (gt.poses[i].copy() if has_gt[i] else None), True
        if not (has_gt[i] and has_gt[i + 1]):
            return None, False
        return se3.interpolate_at(times[i:i + 2], gt.poses[i:i + 2], t_ns), False

    def _noise(self, sequence: str, object_id: str, t_ns: int) -> np.ndarray:
        """A pose perturbation that depends only on (seed, sequence, object, time)."""
        key = int.from_bytes(hashlib.blake2b(f"{sequence}\0{object_id}".encode(), digest_size=8).digest(), "little")
        rng = np.random.default_rng([self.seed & 0xFFFFFFFFFFFFFFFF, key, t_ns & 0xFFFFFFFFFFFFFFFF])
        dt = rng.normal(0.0, self.noise_t_m, 3)
        dr = rng.normal(0.0, self.noise_r_rad, 3)
        return se3.make(so3.exp(dr), dt)

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        name, gt = self._sequence(inp.sequence)
        object_id = inp.object_id or gt.object_id
        if object_id != gt.object_id:
            self.resolve_object(object_id)  # unknown anywhere: UnknownObject
            return EstimateOutput.not_found(f"object '{object_id}' is not in sequence '{name}'")
        T_CO, at_frame = self._pose_at(gt, inp.capture_time_ns)
        if T_CO is None:
            return EstimateOutput.not_found(f"no ground truth of '{object_id}' in '{name}' at {inp.capture_time_ns} ns")
        camera = inp.camera or gt.camera
        x, y, z = T_CO[:3, 3].tolist()  # the object's centre; scalar maths, this runs per frame
        if z <= 0:
            return EstimateOutput.not_found(f"object '{object_id}' is behind the camera")
        u, v = camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy
        if not (0 <= u < camera.width and 0 <= v < camera.height):
            return EstimateOutput.not_found(f"object '{object_id}' centre projects outside the image ({u:.0f}, {v:.0f})")
        if self.noise_t_m or self.noise_r_rad:
            N = self._noise(name, object_id, inp.capture_time_ns)
            T_CO = se3.make(N[:3, :3] @ T_CO[:3, :3], T_CO[:3, 3] + N[:3, 3])
        return EstimateOutput(Status.OK, T_CO, 1.0,
                              covariance=self.covariance if at_frame else self.covariance_interpolated)
