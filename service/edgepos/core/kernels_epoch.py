"""One compiled call for the usual epoch of an IMM/2IMM bank: prediction, gate and correction.

``epoch_step`` runs ``kernels.predict_epoch``, ``kernels.gate_prediction`` and ``kernels.correct_step``
one after the other on the same arrays as their separate calls, so that its results are theirs bit for
bit, and takes the gate's decision in between: when the gate would leave a measurement out (an RSU
pair or a gyro reading beyond its threshold, unless most RSUs fail, when all are kept as
``pipelines.rsu_imu._gate`` keeps them), it stops after the gate and says so. The caller
(``core.compiled.CompiledBankStepper.step``) then finishes the epoch on the per-call path, which
records why each measurement was left out; a failed prediction or correction is finished there too
(the numpy reference repairs or raises). One call instead of three saves the Python around each
(its arguments, its output array, its result objects): with timestamps that jitter, most of an
epoch's time outside the kernels' arithmetic.

The output array: the prediction as ``kernels.predict_step`` writes it (``prediction_size`` long),
then the correction as ``kernels.correct_step`` writes it (``correction_size`` long), then the gate's
squared distances of the RSU pairs and of the gyro readings.
"""

from __future__ import annotations

from edgepos.core.kernels import correct_step, gate_prediction, predict_epoch
from edgepos.core.kernels_base import OK, BoolArray, IntArray, _jit
from edgepos.core.numerics import FloatArray

#: ``epoch_step``'s statuses besides ``kernels_base.OK`` (every part written) and ``FAILED`` (the
#: prediction failed: nothing else written): the gate would leave a measurement out (the prediction
#: and the distances written), or the correction failed (the prediction written).
GATED = 2
CORRECTION_FAILED = 3


@_jit
def epoch_step(
    means: FloatArray,
    covs: FloatArray,
    probabilities: FloatArray,
    transition: FloatArray,
    active: BoolArray,
    common: IntArray,
    phi_slot: int,
    dt: float,
    step_dt: float,
    motion_kinds: IntArray,
    motion_params: FloatArray,
    kinds: IntArray,
    priority: IntArray,
    others: IntArray,
    positions: FloatArray,
    observed_rsus: FloatArray,
    yaw_rates: FloatArray,
    range_variances: FloatArray,
    bearing_variances: FloatArray,
    gyro_variance: float,
    min_speed_sq: float,
    averaged: bool,
    rsu_threshold: float,
    gyro_threshold: float,
    filter_kind: int,
    weights: FloatArray,
    has_centre: bool,
    out: FloatArray,
) -> int:
    """The epoch's prediction over ``dt`` (``step_dt`` for F and Q, as ``predict_epoch``), the gate and
    the correction with every measurement, into ``out`` (see the module docstring). The gate is off
    when ``rsu_threshold`` is negative; ``gyro_threshold`` negative leaves the gyros ungated (a bank
    without acceleration has no yaw-rate prediction). Returns OK, FAILED, GATED or
    CORRECTION_FAILED."""
    count = means.shape[0]
    nc = common.shape[0]
    rsus = positions.shape[0]
    gyros = yaw_rates.shape[0]
    size = 73 * count + nc * (1 + nc)  # prediction_size
    distances = 2 * size + 2 * count  # size + correction_size
    prediction = out[:size]
    status = predict_epoch(
        means,
        covs,
        probabilities,
        transition,
        active,
        common,
        phi_slot,
        dt,
        step_dt,
        motion_kinds,
        motion_params,
        kinds,
        filter_kind,
        weights,
        has_centre,
        prediction,
    )
    if status != OK:
        return status
    if rsu_threshold >= 0.0:
        rsu_distances = out[distances : distances + rsus]
        gyro_distances = out[distances + rsus : distances + rsus + gyros]
        gate_prediction(
            prediction,
            count,
            common,
            positions,
            observed_rsus,
            yaw_rates,
            range_variances,
            bearing_variances,
            gyro_variance,
            min_speed_sq,
            rsu_distances,
            gyro_distances,
        )
        failures = 0
        for r in range(rsus):
            if rsu_distances[r] > rsu_threshold:
                failures += 1
        if failures > 0 and 2 * failures <= rsus:
            return GATED
        if gyro_threshold >= 0.0:
            for g in range(gyros):
                if gyro_distances[g] > gyro_threshold:
                    return GATED
    status = correct_step(
        prediction,
        active,
        common,
        phi_slot,
        priority,
        others,
        positions,
        observed_rsus,
        yaw_rates,
        range_variances,
        bearing_variances,
        gyro_variance,
        min_speed_sq,
        averaged,
        filter_kind,
        weights,
        has_centre,
        out[size:distances],
    )
    return OK if status == OK else CORRECTION_FAILED
