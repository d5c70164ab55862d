"""The `chained` kind: a global estimator for the first pose and after a loss, a local one whenever
a usable prior comes with the frame.

Config (both parts declared above it, by name):

    [[estimators]]
    name = "pvnet_region"
    kind = "chained"
    [estimators.params]
    global = "pvnet"          # finds the object with no prior
    local = "region"          # refines the device's prior
    max_prior_deg = 30.0      # a prior less certain than this (largest rotation sigma) goes global
    max_prior_m = 0.1         # ... or than this (largest translation sigma)
    fallback = true           # a local answer that is not OK (the object lost) is asked of the global one

A prior is usable when it is sent, puts the object in front of the camera and its covariance (when
sent) is within the limits above. The answer's `stage_ms` says which part answered ("global" or
"local", its time in ms).

The chain knows every object of either part. An object only the local part knows (a mesh brought
with `flextrack serve --objects`, which pvnet was never trained on) is answered with a usable prior
only: without one the request is refused (InvalidInput, saying so), and a local answer that is not
OK is returned as it is, there being no global part to fall back to.
"""

from __future__ import annotations

import time

import numpy as np

from estimators.base import EstimateInput, EstimateOutput, Estimator, InvalidInput, Status

PARAMS = {"global", "local", "max_prior_deg", "max_prior_m", "fallback"}


class ChainedEstimator(Estimator):
    kind = "chained"

    def __init__(self, name: str, global_estimator: Estimator, local_estimator: Estimator, *,
                 max_prior_deg: float = 30.0, max_prior_m: float = 0.1, fallback: bool = True):
        super().__init__(name)
        self.global_estimator = global_estimator
        self.local_estimator = local_estimator
        self.max_prior_rad = np.radians(max_prior_deg)
        self.max_prior_m = max_prior_m
        self.fallback = fallback
        self.version = f"{global_estimator.name}@{global_estimator.version}+{local_estimator.name}@{local_estimator.version}"
        self.uses_image = global_estimator.uses_image or local_estimator.uses_image
        self.description = f"{global_estimator.name} without a usable prior, {local_estimator.name} with one"

    @classmethod
    def from_spec(cls, spec) -> ChainedEstimator:
        spec.check_params(PARAMS)
        p = dict(spec.params)
        if "global" not in p or "local" not in p:
            raise ValueError(f"estimator '{spec.name}' (kind chained) needs params `global` and `local` "
                             "(names of estimators declared above it)")
        return cls(spec.name, spec.estimator(p.pop("global")), spec.estimator(p.pop("local")), **p)

    @property
    def objects(self) -> list[str]:
        """Either part's, as they are now (an oracle's grow as sequences are added to it)."""
        return sorted(set(self.global_estimator.objects) | set(self.local_estimator.objects))

    @property
    def ready(self) -> bool:
        return self.global_estimator.ready and self.local_estimator.ready

    def usable_prior(self, inp: EstimateInput) -> bool:
        if inp.prior_T_CO is None or inp.prior_T_CO[2, 3] <= 0:
            return False
        if inp.prior_covariance is None:
            return True
        sigma = np.sqrt(np.maximum(np.diag(inp.prior_covariance), 0.0))
        return bool(sigma[:3].max() <= self.max_prior_rad and sigma[3:].max() <= self.max_prior_m)

    def _run(self, part: Estimator, label: str, inp: EstimateInput) -> EstimateOutput:
        start = time.perf_counter()
        out = part.estimate(inp)
        out.stage_ms = {**out.stage_ms, label: (time.perf_counter() - start) * 1e3}
        return out

    @staticmethod
    def _knows(part: Estimator, object_id: str) -> bool:
        return not part.objects or object_id in part.objects  # no objects: a part that takes any (an oracle)

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        object_id = self.resolve_object(inp.object_id) if self.objects else inp.object_id
        usable = self.usable_prior(inp)
        if usable and self._knows(self.local_estimator, object_id):
            out = self._run(self.local_estimator, "local", inp)
            if out.status == Status.OK or not self.fallback or not self._knows(self.global_estimator, object_id):
                return out
        if not self._knows(self.global_estimator, object_id):
            why = "no prior was sent" if inp.prior_T_CO is None else "the prior is not usable (behind the camera, or " \
                f"less certain than {np.degrees(self.max_prior_rad):g} deg / {self.max_prior_m:g} m per axis)"
            raise InvalidInput(f"estimator '{self.name}' answers object '{object_id}' only from a prior: its global "
                               f"part '{self.global_estimator.name}' does not know it, and {why}; send "
                               "EstimateRequest.prior (a guide view gives a first one: flextrack guide-view)")
        return self._run(self.global_estimator, "global", inp)
