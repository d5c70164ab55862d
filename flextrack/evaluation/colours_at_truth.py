"""An oracle for `flextrack evaluate prior --colours-at-truth`: the region estimator with every fit's first colour
histograms learned at the object's true outline instead of its start's.

Why: on real frames the colour model learned from an outline that is off (the prior's) is what region's accuracy
hinges on (docs/region.md). Scored beside the plain estimator on the same priors, this says how far the estimator
gets when its colours are right, and so what a better colour model could at most bring. It needs the ground truth,
so it is a measurement, never served.
"""

from __future__ import annotations

import numpy as np

from estimators.region.correspondence import project_lines
from estimators.region.estimator import RegionEstimator

TRUE_OUTLINE_MARGIN_PX = 1.0  # as the refit's colours and a session's: 1 px off the outline each side


class ColoursAtTruth(RegionEstimator):
    """`region`, told the truth of the request it is about to answer (`truth_T_CO`, set by the evaluation)."""

    truth_T_CO: np.ndarray | None = None

    def _first_colour_outline(self, model, K, shape, prior_lines, margins):
        if self.truth_T_CO is None:
            return prior_lines, margins
        truth = project_lines(model, self.truth_T_CO[:3, :3], self.truth_T_CO[:3, 3], K, shape)
        if truth is None:
            return prior_lines, margins
        return truth, (TRUE_OUTLINE_MARGIN_PX, TRUE_OUTLINE_MARGIN_PX)
