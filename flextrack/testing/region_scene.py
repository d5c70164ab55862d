"""A rendered view of the default object with a `region` estimator for it: what tests of the region estimator
behind a real server share (a 162-view model built into `cache_dir`, the object 0.8 m away on view 12, over a
plain grey background)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from flextrack import assets
from flextrack.geometry import se3
from flextrack.geometry.camera import PinholeCamera


def rendered_region_scene(cache_dir: str | Path, camera: PinholeCamera):
    """(region estimator, object model, T_CO, RGB frame)."""
    from estimators.objects import load_object
    from estimators.region.estimator import RegionEstimator
    from estimators.region.viewpoint_model import look_at
    from flextrack.simulator.render import Renderer

    obj = load_object("default", assets.default_object_model())
    region = RegionEstimator("region", {"default": obj}, views_subdivisions=2, cache_dir=cache_dir)
    model = region.viewpoint_model("default")
    T = se3.make(*look_at(model.directions[12], model.center, 0.8))
    with Renderer(camera, obj.model_path) as renderer:
        frame = renderer.render(T)
    return region, obj, T, np.where(frame.mask[..., None], frame.rgb, np.uint8(90))
