"""Tightly coupled GNSS + reduced inertial positioning (Jiang & Chen 2018): GPS / BeiDou / Galileo
pseudoranges and optional RISS input (wheel speed, two accelerometers, yaw gyro) into a particle filter,
the paper's unscented particle filter, or a single UKF.

Times: ``t`` of every observation is GPS time of week (s); the week comes from the loaded ephemerides (or
the ``gps_week`` option). Site frame: x east, y north (m) of the local tangent plane at the server's
configured WGS-84 origin, or, without one, at the session's first fix; fixes also carry WGS-84 latitude,
longitude (rad) and ellipsoidal height (m).

Per epoch (observations sharing ``t``):
1. A ``riss`` sample becomes the motion model's input (eq. 2, wheel acceleration from consecutive wheel
   speeds); without a recent one (``riss_timeout``) the GNSS-only constant-velocity model runs. After
   (re)initialisation the GNSS-only model also runs until its velocity gives the azimuth: the RISS model
   integrates the gyro from whatever azimuth it starts with, so it must not start from a guess.
2. Each pseudorange gets its satellite's ECEF position and clock at transmit time: the client's
   ``sat_position``/``sat_clock`` when sent, else the broadcast ephemerides (Earth rotation, satellite
   clock with relativity and group delay); then elevation mask, C/N0 floor, Klobuchar and Saastamoinen at
   the predicted position, and the noise std: the C/N0-elevation model fitted by measurement
   (``noise_model`` fitted, gnss/pseudorange_noise.py) or R0 x the fuzzy factor (Table 1, eq. 20). When the
   environment has differential corrections from the site's reference station (gnss/differential.py),
   each pseudorange with a valid one (same satellite and ephemeris issue, at most
   the correction source's maximum age old) has it added; the others are used uncorrected, and each says why,
   except (``mixed_corrections`` exclude) one of a constellation with two or more corrected satellites: it
   would sit its own model error from their clock, so it is left out (gnss_satellites.leave_out_mixed).
   Before the corrections, a pseudorange with ``carrier_cycles`` (with ``carrier_smoothing`` hatch) is
   replaced by its satellite's carrier-smoothed code (gnss/carrier.py: Hatch filter, a slip by ``lli``,
   Doppler, code-carrier jump or gap restarting only that satellite; the tracks live in the session state),
   its noise std scaled by max(1/sqrt(epochs averaged), ``hatch_std_floor``).
3. The fault test over time (pipelines/gnss_faults.py): a satellite whose innovation against the prediction
   stays beyond the ``fault_probability`` gate is down-weighted, then after ``fault_persistence`` epochs
   excluded until it agrees for ``fault_recovery`` epochs (range and range rate separately). Then a
   snapshot test like the least-squares baseline's (chi-square on this epoch's own least-squares
   residuals, worst pseudorange excluded while it fails; ``fde_probability``) finds biased (NLOS)
   pseudoranges whatever the filter believes; then a residual test against the prediction (per
   constellation, its median removed so a clock error cannot fail every satellite) excludes pseudoranges
   beyond the ``gate_probability`` quantile; when more than half fail the track is lost and the pipeline
   starts again from this epoch's least-squares fix. Last, the integrity monitor (``integrity``,
   pipelines/gnss_integrity.py, gnss/raim.py): solution separation of one-satellite and one-constellation
   hypotheses with the prediction as a prior; the satellite or constellation a failed test points at is
   excluded, and after the update the fix gets its protection level and integrity state.
4. A pseudorange's optional ``doppler_hz`` (with ``use_doppler``) becomes a range rate, -D x wavelength,
   modelled with the satellite's velocity and clock drift from the ephemerides
   (core/measurements/range_rate.py); above the elevation mask it goes through its own residual test
   (one receiver clock drift for all, so the median is removed) and into the same update as the
   pseudoranges, with std ``doppler_std_mps`` x the fuzzy factor.
5. Without a ``riss`` sample in the batch (GNSS-only model), the vehicle constraints join the update as
   pseudo-measurements (pipelines/gnss_constraints.py): zero velocity once the epoch's own Doppler speed has
   stayed low (``zupt``), else, moving, no lateral or vertical velocity (``nhc``); the fix lists them.
6. The filter step; before initialisation, the first epoch with enough satellites initialises the filter
   from a weighted least-squares fix (gnss/spp.py), its velocity and clock drift from the Dopplers when sent.
7. The fix's position covariance (and the prior RAIM tests against) is the filter's times the factor the
   ``error_correlation`` model gives for time-correlated errors (pipelines/gnss_correlation.py), the fix's
   also times the running noise level (``noise_level``, gnss/noise_level.py; corrected rows judged by their
   own reference, pipelines/gnss_correlation.py); the filter's own covariance and gains stay those of
   white errors.
Every pseudorange appears in the fix's measurement list, used (with its noise std and why) or with the
reason it was not, and with its Doppler's use when it carried one.
"""

from __future__ import annotations

import math
import secrets
from collections.abc import Mapping, Sequence
from typing import Any, TypeVar

import numpy as np

from edgepos.core.errors import NumericalError
from edgepos.core.fuzzy import FuzzyNoise
from edgepos.core.measurements.gnss_geometry import delays as epoch_delays
from edgepos.core.measurements.gnss_kernel import epoch_predict
from edgepos.core.measurements.pseudorange import PseudorangeModel
from edgepos.core.measurements.range_rate import RangeRateModel
from edgepos.core.motion import riss as layout
from edgepos.core.motion.riss import GnssOnlyModel
from edgepos.core.observations import Observation, PseudorangeObservation, RissObservation
from edgepos.core.particles import Measurement
from edgepos.core.particles.upf_resample_kernel import epoch_generator
from edgepos.gnss.differential import CorrectionTable
from edgepos.gnss.ephemerides import Ephemerides
from edgepos.gnss.measurements import PseudorangeSet
from edgepos.gnss.orbits import SPEED_OF_LIGHT
from edgepos.gnss.pseudorange_noise import FITTED
from edgepos.gnss.raim import Separations
from edgepos.pipelines.base import (
    Environment,
    Fix,
    InitialState,
    MeasurementUse,
    OptionSpec,
    Pipeline,
    PipelineInputError,
    Problem,
    StateSummary,
    ensure_finite_fixes,
)
from edgepos.pipelines.epochs import group_by_time
from edgepos.pipelines.gnss_constraints import (
    Constraint,
    epoch_constraints,
    with_constraints,
)
from edgepos.pipelines.gnss_correlation import Honesty, honesty, noise_level
from edgepos.pipelines.gnss_faults import (
    centre_rates,
    fault_settings,
    range_innovations,
    rate_innovations,
    screen,
)
from edgepos.pipelines.gnss_integrity import detect_and_exclude, fix_protection, linearisation_ranges
from edgepos.pipelines.gnss_integrity import enabled as integrity_enabled
from edgepos.pipelines.gnss_motion import (
    initialise,
    maybe_start_riss,
    motion_model,
    reset_unseen_clocks,
    session_fix,
    take_riss,
)
from edgepos.pipelines.gnss_options import (
    DEFAULT_DOPPLER_OUTLIER_STD_MPS,
    DEFAULT_DOPPLER_STD_MPS,
    OPTION_SPECS,
    SECONDS_PER_WEEK,
)
from edgepos.pipelines.gnss_satellites import (
    CorrectionUses,
    apply_corrections,
    atmosphere_of,
    carrier_smoothed,
    epoch_satellites,
    leave_out_mixed,
)
from edgepos.pipelines.gnss_screening import (
    DopplerUses,
    left_out,
    range_rate_test,
    residual_test,
    snapshot_std,
    snapshot_test,
)
from edgepos.pipelines.gnss_session import (
    PIPELINE_NAME,
    GnssSession,
    cloud_moments,
    decode_session,
    empty_cloud,
    filter_for,
)
from edgepos.pipelines.gnss_tdcp import TdcpStep, predict_with_displacement, remember_phases
from edgepos.pipelines.gnss_tdcp import enabled as tdcp_enabled
from edgepos.pipelines.gnss_tdcp import report as tdcp_report
from edgepos.pipelines.gnss_validation import validate_batch
from edgepos.pipelines.options import resolve_options

_FUZZY = FuzzyNoise()
"""Table 1's memberships and singletons (one instance: its compiled tables are built once)."""
_INITIAL_CLOCK_DRIFT_STD = 5.0
_INITIAL_DOPPLER_VELOCITY_STD = 1.0
"""Velocity and drift std (m/s) when initialising from a least-squares Doppler velocity: the baseline's
horizontal velocity error on the first half of tests/data/gnss-rover had a 95th percentile of 0.93 m/s."""
_INITIAL_ATTITUDE_STD = 0.1
_HEADING_STD_TO_START_RISS = 0.3
"""The RISS model takes over once the azimuth the velocity implies is known to this std (rad)."""
_MIN_SPEED_FOR_HEADING = 1.0
"""... and both the wheel speed and the estimated speed exceed this (m/s): the heading of a vehicle at rest
is unobservable, and the RISS model would freeze a guess."""


class GnssTightPipeline(Pipeline):
    """GPS/BeiDou/Galileo pseudoranges (+ RISS input) into a UPF, PF or UKF (default UPF with fuzzy noise)."""

    name = PIPELINE_NAME
    description = (
        "Tightly coupled GNSS pseudoranges (GPS, BeiDou, Galileo) and reduced inertial sensors (wheel speed, "
        "accelerometers, yaw gyro) fused by an unscented particle filter with fuzzy noise adaptation "
        "(Jiang & Chen 2018); bootstrap particle filter and UKF as alternatives."
    )
    measurement_kinds = (PseudorangeObservation.kind, RissObservation.kind)

    def option_specs(self) -> list[OptionSpec]:
        return list(OPTION_SPECS)

    def resolve_options(self, options: Mapping[str, Any] | None) -> dict[str, Any]:
        resolved = resolve_options(OPTION_SPECS, options)
        if not resolved["systems"]:
            raise PipelineInputError(
                [Problem(None, "options.systems", "must name at least one constellation")]
            )
        return resolved

    def create(self, options: Mapping[str, Any], initial: InitialState | None) -> bytes:
        options = dict(options)
        seed = options["seed"] if options["seed"] is not None else secrets.randbits(63)
        if initial is not None:
            raise PipelineInputError(
                [Problem(None, "initial", "gnss_tight initialises itself from its first pseudorange epoch")]
            )
        return GnssSession(options, seed, False, None, None, 0, None, None, {}, empty_cloud()).to_bytes()

    def summarise(self, state: bytes) -> StateSummary:
        session = decode_session(state)
        return StateSummary(session.initialised, session.t, session.epochs, {}, session.options)

    def process(
        self, state: bytes, observations: Sequence[Observation], environment: Environment
    ) -> tuple[list[Fix], bytes]:
        session = decode_session(state)
        validate_batch(session.t, observations)
        ephemerides = environment.ephemerides()
        origin = environment.site_origin()
        corrections = environment.corrections()
        riss_in_batch = any(isinstance(o, RissObservation) for o in observations)
        fixes = [
            _step(session, epoch, observations, ephemerides, origin, corrections, riss_in_batch)
            for epoch in group_by_time(observations)
        ]
        return ensure_finite_fixes(fixes), session.to_bytes()


# -- one epoch -----------------------------------------------------------------------------------


def _step(
    session: GnssSession,
    epoch: list[int],
    observations: Sequence[Observation],
    ephemerides: Ephemerides | None,
    origin: tuple[float, float, float] | None,
    corrections: CorrectionTable | None = None,
    riss_in_batch: bool = False,
) -> Fix:
    """One epoch through the filter; every Doppler sent is reported beside its pseudorange, and with
    corrections, each pseudorange's correction."""
    doppler: DopplerUses = {}
    corrected: CorrectionUses = {}
    fix = _filter_epoch(
        session, epoch, observations, ephemerides, origin, doppler, corrections, corrected, riss_in_batch
    )
    if corrections is not None:
        uses = []
        for use in fix.measurements:
            if use.kind == "pseudorange":
                applied, why = corrected.get(use.index, (False, None))
                if not applied and why is None:
                    why = f"its pseudorange was not used: {use.reason}"
                use = _with(use, correction_applied=applied, correction_reason=why)
            uses.append(use)
        fix = _with(fix, measurements=uses)
    carrying = {i for i in epoch if getattr(observations[i], "doppler_hz", None) is not None}
    if not carrying:
        return fix
    reported = []
    for use in fix.measurements:
        if use.index in carrying:
            used, reason = doppler.get(use.index, (False, None))
            if not used and reason is None:
                reason = (
                    f"its pseudorange was not used: {use.reason}" if not use.used else "not in this update"
                )
            use = _with(use, doppler_used=used, doppler_reason=reason)
        reported.append(use)
    return _with(fix, measurements=reported)


_Report = TypeVar("_Report", MeasurementUse, Fix)
_USED = MeasurementUse(0, "pseudorange", True)
"""A used pseudorange's report, copied with its index and noise by ``_with`` (a fifth of ``__init__``'s cost)."""


def _with(report: _Report, **changes: Any) -> _Report:
    """``dataclasses.replace`` for the fix and its per-measurement reports, without running ``__init__``:
    a copy of the instance's fields with ``changes`` over them, a fifth (a report) to a tenth (the fix) of
    replace's cost, which walks the fields in Python every call (an epoch replaces some forty reports and
    three fixes). Valid because neither class has a ``__post_init__`` or slots (its ``__init__`` only
    stores; tests/pipelines/test_pipeline_gnss_shared.py checks both and holds it to replace)."""
    copy = object.__new__(type(report))
    fields = copy.__dict__
    fields.update(report.__dict__)
    fields.update(changes)
    return copy


def _filter_epoch(
    session: GnssSession,
    epoch: list[int],
    observations: Sequence[Observation],
    ephemerides: Ephemerides | None,
    origin: tuple[float, float, float] | None,
    doppler: DopplerUses,
    corrections: CorrectionTable | None,
    corrected: CorrectionUses,
    riss_in_batch: bool = False,
) -> Fix:
    options = session.options
    t = observations[epoch[0]].t
    session.t = t
    session.epochs += 1
    uses: dict[int, MeasurementUse] = {}
    for i in epoch:
        observation = observations[i]
        if isinstance(observation, RissObservation):
            take_riss(session, observation)
            uses[i] = MeasurementUse(i, "riss", True)
    if ephemerides is not None:
        gpst = ephemerides.gpst(t)
    else:
        gpst = (options["gps_week"] or 0) * SECONDS_PER_WEEK + t
    satellites = epoch_satellites(epoch, observations, ephemerides, gpst, options, uses)
    doppler.update({i: (False, reason) for i, reason in satellites.doppler_reasons.items()})
    satellites, smoothing, averaged = carrier_smoothed(session, t, satellites, observations)
    atmosphere = atmosphere_of(options, ephemerides)
    if corrections is not None:
        satellites = apply_corrections(
            satellites, corrections, options, atmosphere.klobuchar is not None, corrected
        )
    rng = epoch_generator(session.seed, session.epochs)  # default_rng([seed, epochs])'s generator

    if session.initialised and session.filter_t is not None and t - session.filter_t > options["max_gap"]:
        session.initialised = False
    if not session.initialised:
        return initialise(
            session,
            t,
            satellites,
            atmosphere,
            origin,
            uses,
            doppler,
            rng,
            "waiting for enough satellites to initialise",
        )

    assert session.anchor is not None
    dt = t - session.filter_t if session.filter_t is not None else 0.0
    model = motion_model(session, t)
    mean, cloud_cov = cloud_moments(session)
    tdcp, delays = TdcpStep(None, {}), None
    if len(satellites.prs) and tdcp_enabled(options):  # the phases' displacement as the motion (gnss_tdcp.py)
        tdcp = predict_with_displacement(session, t, dt, model, mean, satellites, observations, atmosphere)
        if tdcp.model is not None:
            model, (mean, cloud_cov) = tdcp.model, cloud_moments(session)
    centre = model.propagate(mean[None, :], dt)[0]
    active = model.active.copy()
    for system, index in layout.CLOCK.items():
        active[index] = False
    measurement = None
    constraints: list[Constraint] = []
    noise: dict[int, tuple[float, str]] = {}
    rows: np.ndarray = np.zeros(0, dtype=int)
    rate_rows: np.ndarray = np.zeros(0, dtype=int)
    separated: Separations | None = None
    honest = Honesty()
    if len(satellites.prs):
        receiver = session.anchor.ecef(centre)
        iono, tropo, elevation, _ = epoch_delays(atmosphere, receiver, satellites.prs)
        delays = (iono, tropo, elevation)
        rows = np.flatnonzero(elevation >= options["elevation_mask"])
        for row in np.flatnonzero(elevation < options["elevation_mask"]):
            i = satellites.indices[row]
            uses[i] = MeasurementUse(
                i, "pseudorange", False, f"elevation {math.degrees(elevation[row]):.1f} deg below the mask"
            )
        prs = satellites.prs
        if prs.range_rate_mps is not None and prs.sat_clock_drift is not None:
            rate_rows = rows[np.isfinite(prs.range_rate_mps[rows]) & np.isfinite(prs.sat_clock_drift[rows])]
        known = iono + tropo - SPEED_OF_LIGHT * prs.sat_clock_s
        factor = _FUZZY.factor(elevation, prs.cn0_dbhz) if options["fuzzy"] else np.ones(len(prs))
        base_std, model_name = _pseudorange_noise(options, elevation, prs.cn0_dbhz, factor)
        std = base_std * smoothing
        if options.get("mixed_corrections", "use") == "exclude":  # sessions stored before it: use
            rows = leave_out_mixed(satellites, rows, uses)
        predicted_cov = cloud_cov + model.process_noise(dt)
        # one prediction at the centre (and 1 m off it, RAIM's Jacobian) for every test of the epoch
        ranges = linearisation_ranges(session.anchor, centre, prs.sat_position, prs.systems, known)
        rates = centre_rates(session.anchor, centre, prs, rate_rows) if rate_rows.size else None
        fault_reasons: dict[int, str] = {}
        if rows.size and fault_settings(options)[0] > 0.0:
            scores = range_innovations(session, centre, prs, known, std, rows, predicted_cov, ranges[0])
            kept, inflation, fault_reasons = screen(
                session, t, [prs.sats[r] for r in rows.tolist()], scores, rows, "range"
            )
            for r in left_out(rows, kept):
                i = satellites.indices[r]
                uses[i] = MeasurementUse(i, "pseudorange", False, fault_reasons[int(r)])
            std = std.copy()
            std[kept] *= inflation
            rows = kept
        rows = snapshot_test(
            session,
            receiver,
            prs,
            known,
            snapshot_std(elevation, satellites.corrected),
            rows,
            satellites.indices,
            uses,
        )
        rows, lost = residual_test(
            session,
            centre,
            prs,
            known,
            std,
            rows,
            dt,
            model,
            satellites.indices,
            uses,
            predicted_cov,
            ranges[0],
        )
        if lost:
            session.initialised = False
            return initialise(
                session,
                t,
                satellites,
                atmosphere,
                origin,
                uses,
                doppler,
                rng,
                "track lost; waiting for enough satellites",
            )
        honest = honesty(options, rows, std, smoothing, averaged, ranges, prs.systems, predicted_cov, dt)
        if rows.size and integrity_enabled(options):
            rows, separated = detect_and_exclude(
                options,
                session.anchor,
                centre,
                honest.scale(predicted_cov),
                prs.sat_position,
                prs.systems,
                known,
                prs.pseudorange_m,
                std,
                rows,
                satellites.indices,
                prs.sats,
                uses,
                ranges,
            )
        level_in = (
            rows,
            std,
            smoothing,
            averaged,
            ranges,
            prs.systems,
            prs.pseudorange_m,
            satellites.corrected,
        )
        session.noise = noise_level(options, session.noise, t, dt, *level_in)
        rate_std = float(options.get("doppler_std_mps", DEFAULT_DOPPLER_STD_MPS)) * factor
        rate_model: RangeRateModel | None = None
        if rate_rows.size and fault_settings(options)[0] > 0.0:
            scores = rate_innovations(session, centre, prs, rate_std, rate_rows, predicted_cov, rates)
            kept, inflation, rate_reasons = screen(
                session,
                t,
                [prs.sats[r] + "/rate" for r in rate_rows.tolist()],
                scores,
                rate_rows,
                "range rate",
            )
            for r in left_out(rate_rows, kept):
                doppler[satellites.indices[r]] = (False, rate_reasons[int(r)])
            rate_std = rate_std.copy()
            rate_std[kept] *= inflation
            rate_rows = kept
        if rate_rows.size:
            rate_rows = range_rate_test(
                session,
                centre,
                prs,
                rate_std,
                rate_rows,
                dt,
                model,
                satellites.indices,
                doppler,
                predicted_cov,
                rates,
            )
        if rate_rows.size:
            assert prs.sat_velocity is not None and prs.sat_clock_drift is not None
            rate_model = RangeRateModel.build(
                session.anchor,
                prs.sat_position[rate_rows],
                prs.sat_velocity[rate_rows],
                prs.sat_clock_drift[rate_rows],
                rate_std[rate_rows],
            )
        if rows.size or rate_model is not None:
            systems = [prs.systems[r] for r in rows.tolist()]
            if rows.size:
                reset_unseen_clocks(session, t, systems, centre, prs, known, rows, rng)
            for system in set(systems):
                active[layout.CLOCK[system]] = True
            model_pr = PseudorangeModel.build(
                session.anchor, prs.sat_position[rows], systems, known[rows], std[rows]
            )
            measurement = _measurement(options, model_pr, prs.pseudorange_m[rows], rate_model, prs, rate_rows)
            if not riss_in_batch and isinstance(model, GnssOnlyModel):
                constraints = epoch_constraints(session, centre, dt, prs, receiver, elevation, rate_rows)
                measurement = with_constraints(measurement, constraints)
            # the reports' strings from Python floats: formatting numpy scalars costs microseconds each
            base_list, elevation_list, cn0_list = base_std.tolist(), elevation.tolist(), prs.cn0_dbhz.tolist()
            smoothing_list, std_list = smoothing.tolist(), std.tolist()
            for r in rows.tolist():
                why = (
                    f"{model_name} std {base_list[r]:.2f} m at elevation {math.degrees(elevation_list[r]):.0f} "
                    f"deg, C/N0 {cn0_list[r]:.0f} dB-Hz"
                )
                if smoothing_list[r] < 1.0:
                    why += f"; carrier-smoothed: x {smoothing_list[r]:.2f}"
                if r in fault_reasons:
                    why += f"; {fault_reasons[r]}"
                noise[satellites.indices[r]] = (std_list[r], why)
    filt = filter_for(options)
    result = filt.step(session.cloud, model, dt, active, measurement, rng)
    if not (
        np.isfinite(result.mean).all()
        and np.isfinite(result.cov).all()
        and np.isfinite(result.cloud.particles).all()
    ):
        raise NumericalError("the filter step gave a non-finite state")
    session.cloud = result.cloud
    session.filter_t = t
    if measurement is not None and isinstance(model, GnssOnlyModel):
        maybe_start_riss(session, t, result)
    if tdcp_enabled(options):
        remember_phases(session, t, satellites, tdcp, delays, result.mean)
        tdcp_report(uses, noise, satellites.indices, tdcp)
    for r in rows.tolist():
        i = satellites.indices[r]
        noted = noise.get(i)
        uses[i] = _with(
            _USED,
            index=i,
            noise_std=None if noted is None else noted[0],
            noise_reason=None if noted is None else noted[1],
        )
    for r in rate_rows.tolist():
        doppler[satellites.indices[r]] = (True, None)
    if options["filter"] == "pf":  # its particles' covariance collapses (pipelines/gnss_correlation.py)
        honest = honest.floored(result.cov)
    honest = honest.times(session.noise.scale if rows.size else 1.0)
    status = "tracking" if measurement is not None else "predicted"
    dof = int(rows.size + rate_rows.size + sum(len(c.variances) for c in constraints))
    fix = session_fix(t, status, session, result.mean, honest.scale(result.cov), result, dof, uses, origin)
    guard = fix_protection(separated if rows.size else None, fix.position_cov, options)
    return _with(
        fix,
        constraints=tuple(c.name for c in constraints),
        protection_level=guard.level,
        integrity=guard.state,
    )


def _measurement(
    options: Mapping[str, Any],
    model_pr: PseudorangeModel,
    pseudoranges: np.ndarray,
    rate_model: RangeRateModel | None,
    prs: PseudorangeSet,
    rate_rows: np.ndarray,
) -> Measurement:
    """The epoch's update: the pseudoranges, then the range rates when any pass, as one measurement (one
    update, so the filters see their correlation through the shared position and clocks)."""
    outlier = float(options.get("outlier_probability", 0.0)) if options["filter"] != "ukf" else 0.0
    pr_outlier = float(options.get("outlier_std", 30.0)) ** 2
    predict = epoch_predict(model_pr, rate_model)
    if rate_model is None:
        return Measurement(
            predict, pseudoranges, model_pr.variances(), outlier, pr_outlier if outlier > 0.0 else 0.0
        )
    assert prs.range_rate_mps is not None
    rate_outlier = float(options.get("doppler_outlier_std_mps", DEFAULT_DOPPLER_OUTLIER_STD_MPS)) ** 2
    outlier_variance = np.concatenate(
        [np.full(model_pr.dim, pr_outlier), np.full(rate_model.dim, rate_outlier)]
    )
    return Measurement(
        predict,
        np.concatenate([pseudoranges, prs.range_rate_mps[rate_rows]]),
        np.concatenate([model_pr.variances(), rate_model.variances()]),
        outlier,
        outlier_variance if outlier > 0.0 else 0.0,
    )


def _pseudorange_noise(
    options: Mapping[str, Any], elevation: np.ndarray, cn0: np.ndarray, factor: np.ndarray
) -> tuple[np.ndarray, str]:
    """Each pseudorange's std (m) before carrier smoothing and the model's name for the report: the fitted
    C/N0 and elevation model (gnss/pseudorange_noise.py) or R0 x the fuzzy factor. Sessions stored before
    the option existed keep the fuzzy one."""
    if options.get("noise_model", "fuzzy") == "fitted":
        return FITTED.std(elevation, cn0), "fitted C/N0-elevation model:"
    value: np.ndarray = options["pseudorange_std"] * factor
    return value, "R0 x fuzzy factor:" if options["fuzzy"] else "pseudorange_std:"
