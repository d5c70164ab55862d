"""The filter's linearised error dynamics over a run, kept (when asked) to judge its consistency.

A consistent filter's NEES averages to the pose's 6 degrees of freedom, but the mean over one run
scatters as much as its frames' errors are correlated, and the slowly corrected states (rotation,
gyro bias) stay correlated for longer than a 30 s run can show in its own NEES series. The filter
knows how its errors are linked. With tau_k the time of the k-th answer it applied (an anchor):

    x~_k = Psi_k x~_{k-1} + (noise since tau_{k-1}),   Psi_k = (I - K_k H_k) Phi(tau_k, tau_{k-1})
    e(t) = H_t Phi(t, tau_k) x~_k + (noise since tau_k)          (a frame's pose error, wire convention)

so cov(e(t), e(s)) = H_t Phi(t, tau_k) Psi_k ... Psi_{j+1} P_j (H_s Phi(s, tau_j))^T for frames on
anchors k >= j, the process noise between anchors left out (it is small beside P over one answer's
interval). `flextrack.evaluation.consistency` turns that into the interval of a run's mean NEES.

Costs one 19x19 product per IMU sample while on (`FilterOptions.record_error_dynamics`, off by
default), and keeps ~6 kB per answer and ~1 kB per frame: for evaluation runs, not for a device.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class ErrorDynamics:
    # per anchor: (Psi from the previous anchor, None at a (re)start; covariance after the update)
    anchors: list[tuple[np.ndarray | None, np.ndarray]] = field(default_factory=list)
    # per frame, by its camera time: (anchor index, H_t Phi(t, tau_anchor), 6 x N)
    frames: dict[int, tuple[int, np.ndarray]] = field(default_factory=dict)

    def restart(self, cov: np.ndarray) -> None:
        """A (re-)initialisation: a new chain, unlinked to what came before."""
        self.anchors.append((None, cov.copy()))

    def link(self, closed_loop: np.ndarray, cov: np.ndarray) -> None:
        """An applied answer: Psi_k from the previous anchor, and the covariance after the update."""
        self.anchors.append((closed_loop, cov.copy()))

    def frame(self, t_ns: int, pose_map: np.ndarray) -> None:
        """A frame's pose error as a linear map of the current anchor's error."""
        self.frames[t_ns] = (len(self.anchors) - 1, pose_map)
