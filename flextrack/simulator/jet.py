"""Second-order jets in time: a signal with its exact first and second derivatives.

The motion programs are built from these, so that velocity, acceleration, angular velocity and
angular acceleration are exact derivatives of the trajectory (never finite differences), at any
array of times. Arithmetic follows the product and chain rules; arrays broadcast like numpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Jet:
    v: np.ndarray  # value
    d1: np.ndarray  # first time derivative
    d2: np.ndarray  # second time derivative

    @staticmethod
    def const(value, like: Jet) -> Jet:
        v = np.broadcast_to(np.asarray(value, float), np.shape(like.v)).astype(float)
        return Jet(v, np.zeros_like(v), np.zeros_like(v))

    @staticmethod
    def time(t: np.ndarray) -> Jet:
        t = np.asarray(t, float)
        return Jet(t, np.ones_like(t), np.zeros_like(t))

    def __add__(self, other) -> Jet:
        if isinstance(other, Jet):
            return Jet(self.v + other.v, self.d1 + other.d1, self.d2 + other.d2)
        return Jet(self.v + other, self.d1, self.d2)

    __radd__ = __add__

    def __neg__(self) -> Jet:
        return Jet(-self.v, -self.d1, -self.d2)

    def __sub__(self, other) -> Jet:
        return self + (-other)

    def __rsub__(self, other) -> Jet:
        return (-self) + other

    def __mul__(self, other) -> Jet:
        if isinstance(other, Jet):
            return Jet(self.v * other.v, self.d1 * other.v + self.v * other.d1,
                       self.d2 * other.v + 2 * self.d1 * other.d1 + self.v * other.d2)
        return Jet(self.v * other, self.d1 * other, self.d2 * other)

    __rmul__ = __mul__

    def __truediv__(self, other) -> Jet:
        if not isinstance(other, Jet):
            return self * (1.0 / other)
        h = self.v / other.v
        h1 = (self.d1 - h * other.d1) / other.v
        h2 = (self.d2 - 2 * h1 * other.d1 - h * other.d2) / other.v
        return Jet(h, h1, h2)


def sin(f: Jet) -> Jet:
    s, c = np.sin(f.v), np.cos(f.v)
    return Jet(s, c * f.d1, -s * f.d1**2 + c * f.d2)


def cos(f: Jet) -> Jet:
    s, c = np.sin(f.v), np.cos(f.v)
    return Jet(c, -s * f.d1, -c * f.d1**2 - s * f.d2)


def sqrt(f: Jet) -> Jet:
    s = np.sqrt(f.v)
    return Jet(s, f.d1 / (2 * s), f.d2 / (2 * s) - f.d1**2 / (4 * s**3))


def atan2(y: Jet, x: Jet) -> Jet:
    d = x.v**2 + y.v**2
    n = x.v * y.d1 - y.v * x.d1
    n1 = x.v * y.d2 - y.v * x.d2
    d1 = 2 * (x.v * x.d1 + y.v * y.d1)
    return Jet(np.arctan2(y.v, x.v), n / d, (n1 * d - n * d1) / d**2)


def stack(jets: list[Jet]) -> Jet:
    """Components (each (N,)) -> one vector jet (N, k)."""
    return Jet(np.stack([j.v for j in jets], -1), np.stack([j.d1 for j in jets], -1),
               np.stack([j.d2 for j in jets], -1))


def smooth_start(t: np.ndarray, t0: float, ramp: float) -> tuple[Jet, Jet]:
    """(tau, envelope): a clock that stands still before t0 and reaches full speed at t0 + ramp.

    The envelope e rises 0 -> 1 over the ramp with the quintic smoothstep (zero first and second
    derivatives at both ends); tau' = e, so tau = integral of e is C3 and anything driven by tau
    starts from rest with continuous acceleration and jerk: the IMU signal has no steps.
    """
    t = np.asarray(t, float)
    x = np.clip((t - t0) / ramp, 0.0, 1.0)
    e = x**3 * (10 - 15 * x + 6 * x**2)
    e1 = np.where((x > 0) & (x < 1), 30 * x**2 * (1 - x) ** 2 / ramp, 0.0)
    e2 = np.where((x > 0) & (x < 1), 60 * x * (1 - x) * (1 - 2 * x) / ramp**2, 0.0)
    ramp_integral = ramp * x**4 * (2.5 - 3 * x + x**2)  # integral of e over [t0, t0 + x * ramp]
    tau = np.where(t <= t0 + ramp, ramp_integral, ramp / 2 + (t - t0 - ramp))
    return Jet(tau, e, e1), Jet(e, e1, e2)
