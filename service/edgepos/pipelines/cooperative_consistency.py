"""The cooperative pipelines' consistency scale (option ``consistency_scale``): the filter measures how
much larger its error is than its covariance says, from its GNSS fix innovations, and the fix it reports
says so (``core.consistency``).

Why the fix's innovations and not the ranges': a fix's noise is known (its std, or ``gps_std``), so what
its innovations hold beyond that noise is the predicted state's own error. A V2V range's innovation also
holds the neighbour's error and its unknown correlation with this vehicle's (what covariance intersection
exists for): measured on the papers' scenes with the papers' options, the ranges' NIS per dof was 0.92-0.95
for augUKF, whose position NEES per dof was 3-5 (docs/integrity.md, "The fix's consistency scale").

Only what is reported changes: the fix's position covariance (and its correlations with the velocity,
kept) times the scale's estimate, and the protection level's error bounds times its upper confidence
bound (option ``consistency_bound``, on by default): the covariance is the best estimate of the error's
spread (mean NEES near 2), while a protection level must bound the error also when the scale, estimated
from little information, is larger than its estimate. The bound's confidence spends a share
``consistency_risk_share`` of the integrity risk, and the protection level is sized with the rest, so
the two together stay within ``integrity_risk`` (a union bound). The filter's state, its gains, the fault
tests and what the vehicle publishes for its neighbours are the filter's own.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from edgepos.core import gnss_bias
from edgepos.core.consistency import ConsistencyScale, gnss_fix_terms
from edgepos.core.gnss_bias import Bias
from edgepos.core.observations import GnssFixObservation


def observe(
    options: Mapping[str, Any],
    scale: ConsistencyScale,
    mean: np.ndarray,
    cov: np.ndarray,
    bias: Bias,
    fix: GnssFixObservation,
    inflation: float = 1.0,
) -> ConsistencyScale:
    """``scale`` updated with the fix's innovation against the predicted state (``mean``, ``cov``, the
    bias beside it), the fix's white variance as the pipeline's update takes it; ``scale`` itself when the
    session does not keep one. ``inflation``: how much the filter's ``cov`` (and its cross-covariance with
    the bias) exceeds the estimate's whose consistency is measured (``v2x_federated``'s GPS sub-filter is
    the fused estimate reset with P / beta and predicted with Q / beta: 1/beta times the fused prediction)."""
    if not options["consistency_scale"]:
        return scale
    if inflation != 1.0:
        cov = cov / inflation
        bias = Bias(bias.mean, bias.cov, bias.cross / inflation)
    std = fix.std if fix.std is not None else options["gps_std"]
    sigma = options["gnss_bias_std"]
    white = gnss_bias.white_variance(std, sigma) if sigma > 0.0 else std * std
    nis, share, square = gnss_fix_terms(mean, cov, bias, np.array([fix.x, fix.y]), white)
    return scale.updated(fix.t, nis, 2, share, options["consistency_time_constant_s"], square=square)


def factor(options: Mapping[str, Any], scale: ConsistencyScale) -> float:
    """The factor on the fix's reported position covariance: the scale, or 1 when the option is off."""
    return scale.scale if options["consistency_scale"] else 1.0


def protection_scale(
    options: Mapping[str, Any], scale: ConsistencyScale, applies: bool = True
) -> tuple[float, float]:
    """(factor on the protection level's error bounds, share of the integrity risk it spends): (1, 0) when
    the option is off or does not apply (``applies`` false: nothing measured the scale), the estimate's
    factor and 0 with ``consistency_bound`` off, else the upper bound at confidence 1 - share x
    ``integrity_risk`` (infinite, and so the fix unavailable, until the fixes bound it)."""
    if not (options["consistency_scale"] and applies):
        return 1.0, 0.0
    if not options["consistency_bound"]:
        return scale.scale, 0.0
    share = float(options["consistency_risk_share"])
    return scale.upper(1.0 - share * float(options["integrity_risk"])), share
