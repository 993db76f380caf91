"""How a ``gnss_tight`` session moves and starts: the motion model of an epoch (GNSS-only until the
velocity determines the azimuth, then the reduced inertial set), the RISS samples it takes, receiver
clocks of systems not seen for a while, the first fix from a snapshot solution, and the fix an epoch
reports."""

from __future__ import annotations

import functools
import math

import numpy as np

from edgepos.core.motion import riss as layout
from edgepos.core.motion.riss import GeodeticAnchor, GnssOnlyModel, RissInput, RissModel
from edgepos.core.observations import RissObservation
from edgepos.core.particles import Cloud
from edgepos.core.particles.base import StepResult
from edgepos.gnss.geodesy import enu_rotation, geodetic_to_ecef
from edgepos.gnss.measurements import Atmosphere, PseudorangeSet
from edgepos.gnss.orbits import sagnac_range
from edgepos.gnss.spp import SppConfig, SppError, solve_epoch
from edgepos.pipelines.base import (
    Fix,
    MeasurementUse,
)
from edgepos.pipelines.gnss_satellites import (
    EpochSatellites,
    without_mixed,
)
from edgepos.pipelines.gnss_screening import (
    DopplerUses,
)
from edgepos.pipelines.gnss_session import (
    OWN_COVARIANCE_FILTERS,
    GnssSession,
)

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


def maybe_start_riss(session: GnssSession, t: float, result: StepResult) -> None:
    """Let the RISS model take over once the GNSS-only velocity determines the azimuth.

    The azimuth of velocity (v_e, v_n) is atan2(v_e, v_n); its variance is J P_v J^T with
    J = (v_n, -v_e) / |v|^2. The particles already carry the azimuth of their own velocity (the GNSS-only
    model derives it); the UKF's covariance, and the UPF particles' own, get that variance from their
    velocity block, uncorrelated with the rest."""
    riss = session.riss
    if session.heading_known or riss is None or t - riss["t"] > session.options["riss_timeout"]:
        return
    mean, cov = result.mean, result.cov
    ve, vn = float(mean[layout.VE]), float(mean[layout.VN])
    speed2 = ve * ve + vn * vn
    if abs(riss["wheel_speed"]) < _MIN_SPEED_FOR_HEADING or speed2 < _MIN_SPEED_FOR_HEADING**2:
        return
    jacobian = np.array([vn, -ve]) / speed2
    velocity_cov = cov[np.ix_([layout.VE, layout.VN], [layout.VE, layout.VN])]
    variance = float(jacobian @ velocity_cov @ jacobian)
    if not variance <= _HEADING_STD_TO_START_RISS**2:
        return
    session.heading_known = True
    if session.options["filter"] in OWN_COVARIANCE_FILTERS:
        # Their covariance holds the azimuth: until now (GNSS-only) it was derived, not estimated.
        own_velocity = session.cloud.cov[np.ix_([layout.VE, layout.VN], [layout.VE, layout.VN])]
        variance = float(jacobian @ own_velocity @ jacobian)
        cov = session.cloud.cov.copy()
        cov[layout.AZIMUTH, :] = 0.0
        cov[:, layout.AZIMUTH] = 0.0
        cov[layout.AZIMUTH, layout.AZIMUTH] = variance
        session.cloud = Cloud(session.cloud.particles, session.cloud.log_weights, cov)


def motion_model(session: GnssSession, t: float) -> RissModel | GnssOnlyModel:
    options, anchor = session.options, session.anchor
    assert anchor is not None
    riss = session.riss
    if riss is not None and t - riss["t"] <= options["riss_timeout"] and session.heading_known:
        u = RissInput(
            riss["wheel_speed"], riss["wheel_accel"], riss["accel_x"], riss["accel_y"], riss["gyro_z"]
        )
        return RissModel(
            anchor,
            u,
            options["wheel_speed_std"],
            options["accelerometer_std"],
            options["gyro_std"],
            options["clock_bias_psd"],
            options["clock_drift_psd"],
            options["gyro_bias_psd"],
        )
    return GnssOnlyModel(
        anchor,
        options["accel_std"],
        options["vertical_accel_std"],
        options["clock_bias_psd"],
        options["clock_drift_psd"],
    )


def take_riss(session: GnssSession, observation: RissObservation) -> None:
    """Store the sample as the model input; the wheel acceleration is the wheel speed's difference quotient."""
    previous = session.riss
    accel = 0.0
    if previous is not None and 0.0 < observation.t - previous["t"] <= session.options["riss_timeout"]:
        accel = (observation.wheel_speed - previous["wheel_speed"]) / (observation.t - previous["t"])
    session.riss = {
        "t": observation.t,
        "wheel_speed": observation.wheel_speed,
        "wheel_accel": accel,
        "accel_x": observation.accel_x,
        "accel_y": observation.accel_y,
        "gyro_z": observation.gyro_z,
    }


def reset_unseen_clocks(
    session: GnssSession,
    t: float,
    systems: list[str],
    centre: np.ndarray,
    prs: PseudorangeSet,
    known: np.ndarray,
    rows: np.ndarray,
    rng: np.random.Generator,
) -> None:
    """A constellation seen for the first time, or again after a while, restarts its clock bias from the
    median of its pseudoranges' residuals (a bias frozen while it was absent says nothing now)."""
    assert session.anchor is not None
    horizon = max(session.options["riss_timeout"], 5.0)
    cloud = session.cloud
    for system in sorted(set(systems)):
        index = layout.CLOCK[system]
        last = session.clock_seen.get(system)
        if last is None or t - last > horizon:
            members = rows[[s == system for s in systems]]
            receiver = session.anchor.ecef(centre)
            geometric = sagnac_range(prs.sat_position[members], receiver)
            bias = float(np.median(prs.pseudorange_m[members] - geometric - known[members]))
            # Express it at the start of the step: propagation adds drift * dt.
            bias -= float(centre[index] - (cloud.weights @ cloud.particles)[index])
            spread = max(3.0 * session.options["pseudorange_std"], 5.0)
            # The UPF keeps the new uncertainty in each particle's own prior (its UKF proposal resolves it);
            # the PF scatters its particles.
            scatter = len(cloud.particles) > 1 and session.options["filter"] != "upf"
            particles = cloud.particles.copy()
            particles[:, index] = bias + (spread * rng.standard_normal(len(particles)) if scatter else 0.0)
            cov = cloud.cov.copy()
            cov[index, :] = 0.0
            cov[:, index] = 0.0
            cov[index, index] = spread**2
            cloud = Cloud(particles, cloud.log_weights, cov)
        session.clock_seen[system] = t
    session.cloud = cloud


def initialise(
    session: GnssSession,
    t: float,
    satellites: EpochSatellites,
    atmosphere: Atmosphere,
    origin: tuple[float, float, float] | None,
    uses: dict[int, MeasurementUse],
    doppler: DopplerUses,
    rng: np.random.Generator,
    waiting: str,
) -> Fix:
    """Start the filter from this epoch's weighted least-squares fix, or report why it cannot yet. With
    Doppler the fix's least-squares velocity and clock drift start the velocity and drift states."""
    options = session.options
    if options.get("mixed_corrections", "use") == "exclude":  # as the filter's epochs do
        satellites = without_mixed(satellites, uses)
    prs = satellites.prs
    start = (
        None
        if session.anchor is None
        else geodetic_to_ecef(session.anchor.lat, session.anchor.lon, session.anchor.height)
    )
    solution = None
    reason = waiting
    if len(prs) >= 3 + len(set(prs.systems)):
        try:
            solution = solve_epoch(
                prs,
                atmosphere,
                SppConfig(elevation_mask_rad=options["elevation_mask"]),
                start,
                satellites.corrected,
            )
        except SppError as error:
            reason = f"{waiting} (least squares: {error})"
    else:
        reason = f"{waiting} ({len(prs)} usable pseudoranges, {3 + len(set(prs.systems))} needed)"
    if solution is None or not (6.0e6 < float(np.linalg.norm(solution.position)) < 7.0e6):
        for i in satellites.indices:
            uses[i] = MeasurementUse(i, "pseudorange", False, reason)
        return Fix(t=t, status="uninitialised", measurements=[uses[i] for i in sorted(uses)])

    if session.anchor is None:
        session.anchor = (
            GeodeticAnchor(*origin)
            if origin is not None
            else GeodeticAnchor(solution.lat, solution.lon, solution.height)
        )
    anchor = session.anchor
    mean = np.zeros(layout.DIM)
    mean[[layout.NORTH, layout.EAST, layout.UP]] = anchor.offsets(solution.lat, solution.lon, solution.height)
    sigma = options["pseudorange_std"]
    variances = np.zeros(layout.DIM)
    variances[[layout.NORTH, layout.EAST, layout.UP]] = (sigma * solution.dop.pdop) ** 2 / 3.0 + 1.0
    variances[[layout.VE, layout.VN, layout.VU]] = options["init_velocity_std"] ** 2
    variances[[layout.VU]] = min(options["init_velocity_std"], 2.0) ** 2
    velocity = solution.velocity
    if velocity is not None:
        # Rotated from the solution's own east/north/up into the anchor's (they differ by kilometres at most).
        enu = enu_rotation(anchor.lat, anchor.lon) @ velocity.velocity
        mean[[layout.VE, layout.VN, layout.VU]] = enu
        variances[[layout.VE, layout.VN, layout.VU]] = _INITIAL_DOPPLER_VELOCITY_STD**2
        mean[layout.DRIFT] = velocity.clock_drift_mps
    variances[[layout.PITCH, layout.ROLL, layout.AZIMUTH]] = _INITIAL_ATTITUDE_STD**2
    for system, index in layout.CLOCK.items():
        mean[index] = solution.clock_bias_m.get(system, 0.0)
        variances[index] = (sigma * solution.dop.gdop) ** 2
    variances[layout.DRIFT] = (
        _INITIAL_CLOCK_DRIFT_STD if velocity is None else _INITIAL_DOPPLER_VELOCITY_STD
    ) ** 2
    variances[layout.GYRO_BIAS] = options["gyro_bias_std"] ** 2
    variances[layout.WHEEL_SCALE] = options["wheel_scale_std"] ** 2
    cov = np.diag(variances)
    count = 1 if options["filter"] == "ukf" else options["particles"]
    particles = np.repeat(mean[None, :], count, axis=0)
    if options["filter"] == "pf":
        particles += rng.standard_normal((count, layout.DIM)) * np.sqrt(variances)
    # The UPF starts every particle at the fix with the fix's uncertainty as its own prior: its first
    # UKF proposals place them (drawing them here instead would only add variance to the weights).
    particles = GnssOnlyModel.complete(particles)
    session.cloud = Cloud(particles, np.full(count, -math.log(count)), cov)
    session.initialised = True
    session.heading_known = False
    session.filter_t = t
    session.clock_seen = {str(system): t for system in solution.clock_bias_m}

    sats = prs.sats
    row_of = {sat: row for row, sat in enumerate(sats)}
    for sat in solution.sats:
        i = satellites.indices[row_of[sat]]
        uses[i] = MeasurementUse(i, "pseudorange", True)
    for sat in solution.excluded:
        i = satellites.indices[row_of[sat]]
        uses[i] = MeasurementUse(i, "pseudorange", False, "excluded by the least-squares residual test")
    for sat in solution.masked:
        i = satellites.indices[row_of[sat]]
        uses[i] = MeasurementUse(i, "pseudorange", False, "below the elevation mask")
    if velocity is not None:
        for sat in velocity.sats:
            doppler[satellites.indices[row_of[sat]]] = (True, None)
        for sat in velocity.excluded:
            doppler[satellites.indices[row_of[sat]]] = (
                False,
                "excluded by the least-squares Doppler residual test",
            )
    elif prs.has_doppler:
        for i in satellites.indices:
            doppler.setdefault(
                i, (False, "too few Dopplers for the least-squares velocity that starts the filter")
            )
    weights = session.cloud.weights
    estimate = weights @ particles if count > 1 else mean
    return session_fix(t, "initialised", session, estimate, cov, None, len(solution.sats), uses, origin)


def session_fix(
    t: float,
    status: str,
    session: GnssSession,
    mean: np.ndarray,
    cov: np.ndarray,
    result: StepResult | None,
    dof: int,
    uses: dict[int, MeasurementUse],
    origin: tuple[float, float, float] | None,
) -> Fix:
    anchor = session.anchor
    assert anchor is not None
    lat, lon, height = (float(v) for v in anchor.geodetic(mean))
    position = geodetic_to_ecef(lat, lon, height)
    anchor_ecef, rotation = _anchor_frame(anchor.lat, anchor.lon, anchor.height)
    east, north, _ = rotation @ (position - anchor_ecef)
    ve, vn = float(mean[layout.VE]), float(mean[layout.VN])
    riss = session.riss
    yaw_rate = (
        riss["gyro_z"] if riss is not None and t - riss["t"] <= session.options["riss_timeout"] else None
    )
    n, e = layout.NORTH, layout.EAST
    position_cov = [[float(cov[e, e]), float(cov[e, n])], [float(cov[n, e]), float(cov[n, n])]]
    del origin  # the anchor is the origin when one is configured
    return Fix(
        t=t,
        status=status,
        x=float(east),
        y=float(north),
        vx=ve,
        vy=vn,
        speed=math.hypot(ve, vn),
        heading=math.atan2(vn, ve),
        yaw_rate=yaw_rate,
        position_cov=position_cov,
        state_components=layout.NAMES,
        state=[float(v) for v in mean],
        state_cov=cov.tolist(),
        nis=None if result is None else result.nis,
        nis_dof=dof if result is not None and result.nis is not None else 0,
        measurements=[uses[i] for i in sorted(uses)],
        latitude=lat,
        longitude=lon,
        height=height,
    )


@functools.lru_cache(maxsize=256)
def _anchor_frame(lat: float, lon: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """The anchor's ECEF position and east-north-up rotation (read-only), the same every epoch of a
    session: computed once per anchor instead of at every fix."""
    ecef = geodetic_to_ecef(lat, lon, height)
    rotation = enu_rotation(lat, lon)
    ecef.flags.writeable = False
    rotation.flags.writeable = False
    return ecef, rotation
