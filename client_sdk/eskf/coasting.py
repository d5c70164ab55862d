"""Across a gap in the IMU's stream: a constant-velocity motion model, kept on track by the answers alone.

A phone stops delivering samples at times (the `nexus5_ar_a` recording: 23.7 s and 11.9 s). Without
the gyro, the only knowledge of the turn is the answers' own: the filter then estimates the angular
rate from them. It needs no new state for that: while no gyro sample comes, the gyro bias b_g is
unobservable and unused, so its slot holds minus the body's angular rate (the gyro "reads 0", and
w = 0 - b_g is the rate). On entry, the slot takes b_g - w_m (w_m the last sample: the turn goes on);
on exit, b_g comes back as it was, its uncertainty grown by its random walk over the gap. The error
dynamics keep their form: d_theta' = -[w]x d_theta - d_bg, d_p' = d_v, and

    angular acceleration:  d_bg' = n_alpha       (white, density `q_alpha`, rad/s^2/sqrt(Hz))
    linear acceleration:   d_v'  = n_a           (white, density `q_a`, m/s^2/sqrt(Hz))

the gravity and the accelerometer's specific force out of it (the nominal velocity is held). The
process noise of one interval is the exact discrete one of those double integrators (q^2 dt^3 / 3
on the pose, q^2 dt^2 / 2 across): an interval from an answer to a frame is ~0.1 s in one step.

How much a hand turns and shakes between answers is the user's, not the sensor's: the two densities
start at the options' hand-motion guesses and are then fitted to the answers' innovations while the
IMU is silent (`noise_matching.NoiseMatcher`, the rotation block for q_alpha, the position part of the
translation block for q_a), so a calm hand gives a confident, FINE pose and a shaking one an honestly
uncertain one. No per-sample cost: nothing here runs while samples come.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from client_sdk.eskf.noise_matching import NoiseMatcher
from client_sdk.eskf.options import FilterOptions
from client_sdk.eskf.pose_update import skew
from client_sdk.eskf.state import BA, BG, TH, FilterState, N, P, V
from client_sdk.propagation import NS, rotate

_AXES = np.arange(3)
_TH, _P, _V, _BG, _BA = (_AXES + block.start for block in (TH, P, V, BG, BA))  # diagonal indices


def enter(st: FilterState, t_ns: int, w_m: tuple | None, w_var: float, rate_std: float) -> FilterState:
    """`st` (at t_ns, not in a gap) in gap mode: the slot of b_g holds minus the angular rate. `w_m` the raw
    gyro sample at t_ns (None: none recent, the rate is unknown, `rate_std` per axis), `w_var` its noise's
    variance per axis."""
    c, cov = st.c, st.cov.copy()
    held = (tuple(c[0:3]), st.cov[BG, BG].copy(), t_ns)
    if w_m is None:
        slot = (0.0, 0.0, 0.0)
        cov[BG, :] = 0.0
        cov[:, BG] = 0.0
        cov[BG, BG] = np.eye(3) * rate_std ** 2
    else:  # -w = b_g - w_m: its error is the bias's plus the sample's noise
        slot = (c[0] - w_m[0], c[1] - w_m[1], c[2] - w_m[2])
        cov[BG, BG] += np.eye(3) * w_var
    return replace(st, c=slot + tuple(c[3:]), cov=cov, held=held)


def leave(st: FilterState, t_ns: int, gyro_walk: float) -> FilterState:
    """`st` (at t_ns, in gap mode) back to normal: b_g as it was before the gap, its variance grown by its
    random walk over the gap, no longer correlated with the rest (the rate estimate is dropped: the gyro
    measures it again)."""
    b_g, P_bg, t_enter = st.held
    cov = st.cov.copy()
    cov[BG, :] = 0.0
    cov[:, BG] = 0.0
    cov[BG, BG] = P_bg + np.eye(3) * gyro_walk ** 2 * max(t_ns - t_enter, 0) * NS
    return replace(st, c=tuple(b_g) + tuple(st.c[3:]), cov=cov, held=None)


def rate(c: tuple) -> tuple:
    """The body's angular rate a gap-mode state holds."""
    return (-c[0], -c[1], -c[2])


def step_x(x: tuple, c: tuple, dt: float) -> tuple:
    """The nominal state dt seconds on: turning at the held rate, moving at the held velocity."""
    R = rotate(x, -c[0] * dt, -c[1] * dt, -c[2] * dt)
    return R + (x[9] + dt * x[12], x[10] + dt * x[13], x[11] + dt * x[14]) + tuple(x[12:15])


def transition(c: tuple, dt: float) -> np.ndarray:
    """Phi over dt seconds in gap mode (first order in the rotation, exact in the rest)."""
    w0, w1, w2 = (-c[0] * dt, -c[1] * dt, -c[2] * dt)
    phi = np.eye(N)
    phi[TH, TH] = np.array([[1.0, w2, -w1], [-w2, 1.0, w0], [w1, -w0, 1.0]])  # I - [w dt]x
    phi[TH, BG] = -np.eye(3) * dt
    phi[P, V] = np.eye(3) * dt
    return phi


def step_cov(cov: np.ndarray, c: tuple, dt: float, q_alpha: float, q_a: float, accel_walk: float
             ) -> tuple[np.ndarray, np.ndarray]:
    """(covariance dt seconds on, Phi) in gap mode, with the exact discrete noise of the two double integrators."""
    phi = transition(c, dt)
    out = np.dot(np.dot(phi, cov), phi.T)
    d3, d2 = dt ** 3 / 3.0, dt * dt / 2.0
    qa2, qv2 = q_alpha * q_alpha, q_a * q_a
    out[_TH, _TH] += qa2 * d3
    out[_TH, _BG] -= qa2 * d2  # d_theta' = -d_bg
    out[_BG, _TH] -= qa2 * d2
    out[_BG, _BG] += qa2 * dt
    out[_P, _P] += qv2 * d3
    out[_P, _V] += qv2 * d2
    out[_V, _P] += qv2 * d2
    out[_V, _V] += qv2 * dt
    out[_BA, _BA] += accel_walk ** 2 * dt
    return out, phi


class GapNoise:
    """The two hand-motion densities in use, fitted to the answers' innovations across gaps."""

    def __init__(self, options: FilterOptions, memory_answers: float) -> None:
        self._prior = (options.gap_angular_accel_density, options.gap_accel_density)
        # the answers' own noise can hide the hand's motion from the fit (it then reads ~0), never make it vanish
        self._floor = tuple(0.1 * p for p in self._prior)
        self._matchers = (NoiseMatcher(memory_answers, 3), NoiseMatcher(memory_answers, 3))
        self._adapt = options.match_gap_noise

    @property
    def densities(self) -> tuple[float, float]:
        """(q_alpha rad/s^2/sqrt(Hz), q_a m/s^2/sqrt(Hz)) in use: the fit from the first answer in a gap on,
        between the floor and the prior (a start's few answers scatter it; the prior bounds how far up; a
        prior held for 20 answers kept ~1.4 s of frames 4-5 px off at a 1-sigma of 60 px, `nexus5_ar_a`)."""
        out = []
        for m, prior, floor in zip(self._matchers, self._prior, self._floor):
            fit = m.early_fit if self._adapt else None
            out.append(prior if fit is None else min(prior, max(math.sqrt(max(fit, 0.0)), floor)))
        return out[0], out[1]

    def add(self, r: np.ndarray, S: np.ndarray, Rp: np.ndarray, dt: float) -> None:
        """One answer `dt` s after the last, both in one gap: residual r, its covariance S (wire convention),
        Rp = R_CO p_OB (the translation block's lever on the rotation error, taken out of it first)."""
        if not self._adapt:
            return
        M = np.eye(6)
        M[3:6, 0:3] = -skew(Rp)  # r_t - [Rp]x r_rot: the position's part, free of the rotation error's
        r2, S2 = M @ r, M @ S @ M.T
        now = self.densities
        for m, d, lo in zip(self._matchers, now, (0, 3)):
            Sb = S2[lo:lo + 3, lo:lo + 3]
            m.add(float(r2[lo:lo + 3] @ r2[lo:lo + 3]), float(np.trace(Sb)), d, dt, float(np.sum(Sb * Sb)))
