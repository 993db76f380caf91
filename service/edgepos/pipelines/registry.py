"""Every pipeline a session can use, by name: a new pipeline is one module plus one line here.

Each is wrapped in ``plausibility.Plausible``: fixes that break a physical bound are reported
"diverged" (and by default reset the session), whatever the pipeline; and outside that in
``lag.LagWindow``: late measurements are inserted at their own time and earlier fixes revised."""

from __future__ import annotations

from edgepos.pipelines.base import Pipeline
from edgepos.pipelines.gnss_tight import GnssTightPipeline
from edgepos.pipelines.lag import LagWindow
from edgepos.pipelines.plausibility import Plausible
from edgepos.pipelines.rsu_imu import RsuImuPipeline
from edgepos.pipelines.v2v_coop import V2vCoopPipeline
from edgepos.pipelines.v2x_federated import V2xFederatedPipeline

PIPELINES: dict[str, Pipeline] = {
    pipeline.name: LagWindow(Plausible(pipeline))
    for pipeline in (RsuImuPipeline(), V2vCoopPipeline(), V2xFederatedPipeline(), GnssTightPipeline())
}


def get_pipeline(name: str) -> Pipeline:
    """The registered pipeline ``name``; KeyError if there is none."""
    return PIPELINES[name]
