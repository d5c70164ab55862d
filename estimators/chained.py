"""The `chained` kind: a global estimator for the first pose and after a loss, a local one whenever
a usable prior comes with the frame, and the global one again now and then to re-anchor the local one.

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
    global_every = 10         # every 10th request of a session goes global even with a usable prior (0: never)

A prior is usable when it is sent, puts the object in front of the camera and its covariance (when
sent) is within the limits above. A local estimator refines the prior it is given, and what it cannot
see it keeps: `region` fits an outline, which says little about a turn out of the image plane, so a
device's pose that is off that way is answered off that way, frame after frame (docs/region.md, Not
done: on `table2 --backend pvnet_region` a tracked rotation about 1 deg off for the whole run). Every
`global_every`-th request of a session (counted per session and object, the count bounded like
region's sessions) is therefore asked of the global part, which does not start from the prior; when it
does not answer OK, the local part answers that request as usual. Requests without a session id are
never re-anchored. The answer's `stage_ms` says which part answered ("global" or
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
from estimators.session_store import SessionStore

PARAMS = {"global", "local", "max_prior_deg", "max_prior_m", "fallback", "global_every"}


class ChainedEstimator(Estimator):
    kind = "chained"

    def __init__(self, name: str, global_estimator: Estimator, local_estimator: Estimator, *,
                 max_prior_deg: float = 30.0, max_prior_m: float = 0.1, fallback: bool = True,
                 global_every: int = 10):
        super().__init__(name)
        self.global_estimator = global_estimator
        self.local_estimator = local_estimator
        self.max_prior_rad = np.radians(max_prior_deg)
        self.max_prior_m = max_prior_m
        self.fallback = fallback
        if global_every < 0:
            raise ValueError(f"estimator '{name}': global_every must be >= 0 (0: never), got {global_every}")
        self.global_every = int(global_every)
        self._counts: SessionStore[list[int]] = SessionStore(lambda: [0])
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

    def _reanchor_due(self, inp: EstimateInput, object_id: str) -> bool:
        """Whether this request is its session's `global_every`-th since the last re-anchoring."""
        if not self.global_every or not inp.session_id or not self._knows(self.global_estimator, object_id):
            return False
        count, _ = self._counts.get((inp.session_id, object_id))
        count[0] += 1
        return count[0] % self.global_every == 0

    def estimate(self, inp: EstimateInput) -> EstimateOutput:
        object_id = self.resolve_object(inp.object_id) if self.objects else inp.object_id
        usable = self.usable_prior(inp)
        if usable and self._knows(self.local_estimator, object_id):
            if self._reanchor_due(inp, object_id):
                out = self._run(self.global_estimator, "global", inp)
                if out.status == Status.OK:
                    return out
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
