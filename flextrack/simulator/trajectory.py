"""The paper's motion programs (Table 3): translational and circular, easy / medium / hard.

Each program is an analytic function of time (sums of sinusoids driven by a clock that starts
from rest), so the camera's pose, velocity, acceleration, angular velocity and angular
acceleration are exact at any time. World W: z up, the object's centre at `target_W`; time 0 is
the start of the IMU record; the device is held still until `still_s`, then the program eases in
over `ramp_s` and runs to `still_s + duration_s`.

Distance: the device starts 1.2 m from the object (the paper's "initial distance ... about 1.2
meters") and, while the program eases in, moves in to a working distance of about 0.95 m
(`WORK_DISTANCE_M`), as a user steps closer to what they look at. The approach rides on the ramp's
envelope, so it is over before the steady part whose accelerations Table 3 lists; its speed counts
in the averages. At 1.2 m a 15 cm object covers about frame area / 100, the paper's PIA threshold
for a lost track; at ~0.95 m it covers about twice that.

- translational: dolly (along the view), pedestal (up/down) and truck (sideways) about a nominal
  pose at the working distance, looking at the object; a small scripted sway of the orientation on
  the medium and hard levels. The object stays near the image centre.
- circular: the camera orbits the object, always looking at it, with a slow tangential/vertical
  loop centred on the working distance (so the distance stays near it), and (medium, hard) a steady
  roll about the optical axis, so that the angular rate reaches Table 3's.
- static: held still throughout (for noise studies: the Allan deviation).
- shake: band-limited random sums of sinusoids (0.4-2.5 Hz, seeded) on position and on three
  small rotation angles, scaled to an RMS speed / angular rate that grows with the level.

`scripted=False` leaves the shake out, for the statistics Table 3 lists for the script.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flextrack.simulator import jet
from flextrack.simulator.jet import Jet
from flextrack.simulator.kinematics import Kinematics, compose_rotations

MOTIONS = ("translational", "circular", "static")
LEVELS = ("easy", "medium", "hard")

# Table 3 of the paper: avg speed m/s, accel range m/s^2, avg angular rate rad/s, angular accel range rad/s^2.
TABLE3 = {
    ("translational", "easy"): (0.062, (0.0, 0.191), 0.001, (0.0, 0.0)),
    ("translational", "medium"): (0.123, (0.173, 0.364), 0.014, (0.0, 0.152)),
    ("translational", "hard"): (0.182, (0.346, 0.537), 0.041, (0.151, 0.303)),
    ("circular", "easy"): (0.073, (0.010, 0.016), 0.056, (0.0, 0.038)),
    ("circular", "medium"): (0.147, (0.039, 0.063), 0.330, (0.0, 0.150)),
    ("circular", "hard"): (0.229, (0.088, 0.140), 0.402, (0.0, 0.338)),
}

# Camera looking along world +x, image x = world -y, image y = world -z (down).
R_WC_LOOK_X = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
X, Y, Z = np.eye(3)


@dataclass(frozen=True)
class Translational:
    """p = c0 + loop of radius r_loop in the truck/pedestal plane + dolly + slow truck drift."""

    r_loop: float
    w_loop: float
    dolly: float
    w_dolly: float
    drift: float
    w_drift: float
    pedestal: float  # slow pedestal swing (easy level)
    w_pedestal: float
    sway: float  # rad, scripted coning of the orientation
    w_sway: float


@dataclass(frozen=True)
class Circular:
    """Orbit at rate w_orbit, a tangential/vertical loop of radius r_loop, a steady roll."""

    w_orbit: float
    r_loop: float
    w_loop: float
    roll_rate: float


@dataclass(frozen=True)
class Shake:
    speed_rms: float  # m/s
    rate_rms: float  # rad/s


PROGRAMS = {
    ("translational", "easy"): Translational(0.0, 1.0, 0.24, 0.22, 0.24, 0.27, 0.09, 0.41, 0.0, 1.0),
    ("translational", "medium"): Translational(0.047, 2.1, 0.040, 2.6, 0.06, 0.3, 0.0, 1.0, 0.006, 2.2),
    ("translational", "hard"): Translational(0.0555, 2.6, 0.085, 2.0, 0.06, 0.3, 0.0, 1.0, 0.0068, 5.7),
    ("circular", "easy"): Circular(0.0235, 0.239, 0.2104, 0.0),
    ("circular", "medium"): Circular(0.1317, 0.1632, 0.5033, 0.3511),
    ("circular", "hard"): Circular(0.2075, 0.1709, 0.7228, 0.4162),
}
_STILL = Translational(0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0, 0.0, 1.0)
PROGRAMS.update({("static", level): _STILL for level in LEVELS})  # held still throughout (noise studies)
SHAKES = {
    ("translational", "easy"): Shake(0.004, 0.0011),
    ("translational", "medium"): Shake(0.010, 0.007),
    ("translational", "hard"): Shake(0.016, 0.016),
    ("circular", "easy"): Shake(0.025, 0.010),
    ("circular", "medium"): Shake(0.010, 0.030),
    ("circular", "hard"): Shake(0.016, 0.045),
    **{("static", level): Shake(0.0, 0.0) for level in LEVELS},
}
DISTANCE_M = 1.2  # camera to object centre at the start (the paper's initial distance)
WORK_DISTANCE_M = 0.95  # reached by the end of the ramp (see module doc)
ELEVATION_RAD = np.radians(25.0)  # camera above the object, looking down at it
SHAKE_BAND_HZ = (0.4, 2.5)
SHAKE_TONES = 8


def look_at_angles(offset_W: np.ndarray) -> tuple[float, float]:
    """(yaw, pitch-down) of a camera at `offset_W` from its target that looks at the target."""
    yaw = float(np.arctan2(-offset_W[1], -offset_W[0]))
    pitch = float(np.arctan2(offset_W[2], np.hypot(offset_W[0], offset_W[1])))
    return yaw, pitch


def _sum_of_sines(tau: Jet, amps: np.ndarray, omegas: np.ndarray, phases: np.ndarray) -> Jet:
    """sum_k amps[k] * sin(omegas[k] * tau + phases[k]) - its value at tau = 0 (starts at 0)."""
    total = Jet.const(0.0, tau)
    for a, w, ph in zip(amps, omegas, phases):
        total = total + a * (jet.sin(tau * w + ph) - np.sin(ph))
    return total


class MotionProgram:
    """One camera trajectory: `camera(t)` gives its exact kinematics at times t (s)."""

    def __init__(self, motion: str, level: str, seed: int = 0, *, still_s: float = 2.0, duration_s: float = 30.0,
                 ramp_s: float = 2.0, target_W: np.ndarray = (0.0, 0.0, 0.0)):
        if (motion, level) not in PROGRAMS:
            raise ValueError(f"unknown motion program {motion}/{level}: motion in {MOTIONS}, level in {LEVELS}")
        if still_s < 0 or duration_s <= 0 or ramp_s <= 0:
            raise ValueError("still_s >= 0, duration_s > 0 and ramp_s > 0 are required")
        self.motion, self.level, self.seed = motion, level, int(seed)
        self.still_s, self.duration_s, self.ramp_s = float(still_s), float(duration_s), float(ramp_s)
        self.target_W = np.asarray(target_W, float)
        self.params = PROGRAMS[(motion, level)]
        self.shake = SHAKES[(motion, level)]
        rng = np.random.default_rng([self.seed, LEVELS.index(level), MOTIONS.index(motion)])
        self.heading = float(rng.uniform(-np.pi, np.pi))  # where the camera starts around the object
        self._shake_tones = self._draw_shake(rng)

    @property
    def end_s(self) -> float:
        return self.still_s + self.duration_s

    def _draw_shake(self, rng: np.random.Generator) -> dict[str, tuple[np.ndarray, ...]]:
        """Per channel (3 position, 3 angle) frequencies, phases and unit-RMS-rate amplitudes."""
        tones = {}
        for name, target in (("pos", self.shake.speed_rms), ("rot", self.shake.rate_rms)):
            omegas = 2 * np.pi * rng.uniform(*SHAKE_BAND_HZ, size=(3, SHAKE_TONES))
            phases = rng.uniform(0, 2 * np.pi, size=(3, SHAKE_TONES))
            amps = rng.uniform(0.5, 1.0, size=(3, SHAKE_TONES)) / omegas  # ~1/f: hand sway
            rms_rate = np.sqrt(np.sum((amps * omegas) ** 2) / 2)  # exact for distinct tones
            tones[name] = (amps * target / rms_rate, omegas, phases)
        return tones

    def _clock(self, t: np.ndarray) -> tuple[Jet, Jet]:
        return jet.smooth_start(t, self.still_s, self.ramp_s)

    def camera(self, t: np.ndarray, scripted: bool = False) -> Kinematics:
        """Exact kinematics of the camera C at times t (s); `scripted` leaves the shake out."""
        t = np.atleast_1d(np.asarray(t, float))
        tau, envelope = self._clock(t)
        if self.motion != "circular":
            pos, factors = self._translational(tau, envelope)
        else:
            pos, factors = self._circular(tau, envelope)
        if not scripted:
            amps, omegas, phases = self._shake_tones["pos"]
            shake_pos = jet.stack([_sum_of_sines(tau, *ch) * envelope for ch in zip(amps, omegas, phases)])
            pos = pos + shake_pos
            amps, omegas, phases = self._shake_tones["rot"]
            for axis, ch in zip((Z, Y, X), zip(amps, omegas, phases)):  # yaw, pitch, roll in the camera
                factors.append((axis, _sum_of_sines(tau, *ch) * envelope))
        R, w, alpha = compose_rotations(factors, len(t))
        return Kinematics(R, pos.v, pos.d1, pos.d2, w, alpha)

    def _approach(self, envelope: Jet) -> Jet:
        """Distance moved towards the object: 0 while still, DISTANCE_M - WORK_DISTANCE_M after the ramp."""
        if self.motion == "static":
            return 0.0 * envelope
        return (DISTANCE_M - WORK_DISTANCE_M) * envelope

    def _translational(self, tau: Jet, envelope: Jet) -> tuple[Jet, list]:
        p = self.params
        offset = DISTANCE_M * np.array([np.cos(ELEVATION_RAD) * np.cos(self.heading),
                                        np.cos(ELEVATION_RAD) * np.sin(self.heading), np.sin(ELEVATION_RAD)])
        yaw, pitch = look_at_angles(offset)
        R0 = _look_rotation(yaw, pitch)
        truck, up, view = R0[:, 0], -R0[:, 1], R0[:, 2]  # orthogonal: |a| of loop + dolly stays bounded
        zero = Jet.const(0.0, tau)
        loop_a = p.r_loop * (jet.sin(tau * p.w_loop))
        loop_b = p.r_loop * (jet.cos(tau * p.w_loop) - 1.0)
        dolly = p.dolly * jet.sin(tau * p.w_dolly) + self._approach(envelope)
        drift = p.drift * jet.sin(tau * p.w_drift)
        pedestal = p.pedestal * jet.sin(tau * p.w_pedestal)
        comps = []
        for i in range(3):
            c = zero + (self.target_W[i] + offset[i])
            c = c + (loop_a + drift) * truck[i] + (loop_b + pedestal) * up[i] + dolly * view[i]
            comps.append(c)
        factors = [R0]
        if p.sway > 0:
            factors += [(Y, p.sway * jet.sin(tau * p.w_sway)), (X, p.sway * (jet.cos(tau * p.w_sway) - 1.0))]
        return jet.stack(comps), factors

    def _circular(self, tau: Jet, envelope: Jet) -> tuple[Jet, list]:
        p = self.params
        # Start at DISTANCE_M; during the ramp move in and down so that the loop below is centred
        # on a point WORK_DISTANCE_M from the object at the same elevation.
        work_r, work_h = WORK_DISTANCE_M * np.cos(ELEVATION_RAD), WORK_DISTANCE_M * np.sin(ELEVATION_RAD)
        r = DISTANCE_M * np.cos(ELEVATION_RAD) + (work_r - DISTANCE_M * np.cos(ELEVATION_RAD)) * envelope
        height = DISTANCE_M * np.sin(ELEVATION_RAD) + (work_h - p.r_loop - DISTANCE_M * np.sin(ELEVATION_RAD)) * envelope
        # A loop in the tangential/vertical plane on top of the orbit: the tangential part is an
        # azimuth swing, so the orbit keeps its radius.
        azimuth = self.heading + tau * p.w_orbit + (p.r_loop / work_r) * jet.sin(tau * p.w_loop)
        h = height + p.r_loop * (1.0 - jet.cos(tau * p.w_loop))
        pos = jet.stack([self.target_W[0] + r * jet.cos(azimuth), self.target_W[1] + r * jet.sin(azimuth),
                         h + self.target_W[2]])
        yaw = azimuth + np.pi
        pitch = jet.atan2(h, r)
        factors = [(Z, yaw), R_WC_LOOK_X, (X, -1.0 * pitch)]
        if p.roll_rate > 0:
            factors.append((Z, tau * p.roll_rate))
        return pos, factors

    def statistics(self, rate_hz: float = 1000.0) -> dict:
        """Table 3's figures for this sequence: scripted and with shake, over the moving part."""
        t = np.arange(self.still_s, self.end_s, 1.0 / rate_hz)
        steady = t >= self.still_s + self.ramp_s
        if not steady.any():  # a program shorter than its ramp: no steady part
            steady[:] = True
        out = {"note": "ranges are min..max over the steady part (after the start ramp); averages over the motion"}
        for name, scripted in (("scripted", True), ("with_shake", False)):
            k = self.camera(t, scripted=scripted)
            speed, acc = np.linalg.norm(k.v_WX, axis=1), np.linalg.norm(k.a_WX, axis=1)
            rate, ang_acc = np.linalg.norm(k.w_X, axis=1), np.linalg.norm(k.alpha_X, axis=1)
            out[name] = {
                "avg_speed_m_s": float(speed.mean()),
                "accel_range_m_s2": [float(acc[steady].min()), float(acc[steady].max())],
                "avg_angular_rate_rad_s": float(rate.mean()),
                "angular_accel_range_rad_s2": [float(ang_acc[steady].min()), float(ang_acc[steady].max())],
            }
        if (self.motion, self.level) not in TABLE3:
            return out
        speed, acc_range, rate, ang_range = TABLE3[(self.motion, self.level)]
        out["table3"] = {"avg_speed_m_s": speed, "accel_range_m_s2": list(acc_range),
                         "avg_angular_rate_rad_s": rate, "angular_accel_range_rad_s2": list(ang_range)}
        return out


def _look_rotation(yaw: float, pitch_down: float) -> np.ndarray:
    """R_WC of a camera with the given heading (about world z) and downward pitch, no roll."""
    cz, sz = np.cos(yaw), np.sin(yaw)
    Rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    c, s = np.cos(-pitch_down), np.sin(-pitch_down)
    Rx = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    return Rz @ R_WC_LOOK_X @ Rx
