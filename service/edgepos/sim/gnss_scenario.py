"""Scenarios of the GNSS + RISS simulation: site, route, city, receiver and sensor error models.

The site is downtown Nanjing (Xinjiekou, 32.0415 N 118.7845 E, 15 m ellipsoidal height), where Jiang
and Chen's test drive was: a street grid whose x axis is east and y axis north (the local tangent plane
at the site, which is also the pipeline's site origin). All parameters are plain dataclasses; the numbers
are the defaults of :func:`urban_scenario` and each says where it comes from in docs/gnss-simulation.md.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from edgepos.sim.constellation import Constellation, gps_bds_constellation
from edgepos.sim.gnss_carrier import CarrierModel
from edgepos.sim.gnss_doppler import DopplerModel
from edgepos.sim.trajectory import Segment, Truth
from edgepos.sim.urban import CityParameters, StreetView, drive, nanjing_route, short_route, street_view

NANJING_SITE = (math.radians(32.0415), math.radians(118.7845), 15.0)
#: GPS week 1980 (2017-12-17), Wednesday 02:00 GPST; only the constellation's own epoch matters.
GPS_WEEK = 1980
START_TOW_S = 3 * 86400.0 + 2 * 3600.0
#: The drive starts eastbound (heading counter-clockwise from east), as first designed. It was northbound
#: for a while only because the gnss_tight pipeline started the RISS azimuth at north and could not recover
#: an eastbound start; the pipeline now waits for the GNSS velocity to give the azimuth.
START_HEADING = 0.0


@dataclass(frozen=True)
class SignalModel:
    """C/N0, noise, multipath and NLOS of the pseudoranges."""

    horizon_mask_rad: float = math.radians(5.0)
    """Satellites below this elevation are never tracked (terrain, antenna gain)."""
    cn0_zenith_dbhz: float = 48.0
    cn0_horizon_dbhz: float = 34.0
    """LOS C/N0 = horizon + (zenith - horizon) sin(elevation), before noise."""
    cn0_geo_loss_db: float = 2.0
    """BeiDou GEO/IGSO signals arrive weaker (longer path)."""
    cn0_walk_db: float = 1.5
    cn0_walk_tau_s: float = 5.0
    cn0_white_db: float = 1.0
    tracking_threshold_dbhz: float = 25.0
    """Signals below this C/N0 are not tracked (not reported)."""
    code_noise_m: float = 0.25
    """Code tracking noise at 45 dB-Hz; scales with 10^((45 - C/N0) / 20)."""
    multipath_floor_m: float = 0.3
    multipath_low_m: float = 3.0
    multipath_scale_rad: float = math.radians(15.0)
    """LOS multipath std = floor + low exp(-elevation / scale)."""
    multipath_tau_s: float = 3.0
    """Correlation time of multipath (first-order Gauss-Markov)."""
    nlos_probability: float = 0.5
    """A masked satellite above the horizon mask arrives reflected with this probability, drawn per
    satellite and place (street block or gap) so it persists while the vehicle stays there."""
    nlos_loss_db: tuple[float, float] = (6.0, 14.0)
    """Reflection loss (uniform range), per satellite and place."""
    nlos_extra_m: tuple[float, float] = (0.0, 10.0)
    """Extra delay beyond the specular façade path (diffuse and multiple reflections), uniform."""


@dataclass(frozen=True)
class ReceiverModel:
    """Receiver clock, atmosphere residuals and broadcast orbit/clock errors."""

    clock_bias_range_m: float = 3.0e4
    """GPS clock bias at the start: uniform in +-this (100 us)."""
    inter_system_bias_m: float = 10.0
    """BeiDou - GPS receiver bias: N(0, this^2)."""
    clock_drift_std_mps: float = 1.0
    """Initial drift N(0, this^2) m/s (a steered TCXO)."""
    clock_bias_psd: float = 0.01
    """Random walk of the bias (m^2/s): c^2 h0 / 2 of a TCXO (h0 ~ 2e-19)."""
    clock_drift_psd: float = 0.04
    """Random walk of the drift (m^2/s^3): c^2 2 pi^2 h_-2 (h_-2 ~ 2e-20)."""
    iono_vertical_residual_m: float = 1.0
    """Vertical ionosphere left after the broadcast (Klobuchar) correction: N(0, this^2) per run, mapped
    with Klobuchar's obliquity factor and scaled to each frequency."""
    iono_satellite_m: float = 0.3
    """Per-satellite part of that residual (pierce points differ): N(0, this^2) per run."""
    tropo_fraction: float = 0.05
    """True troposphere = Saastamoinen x (1 + N(0, this^2)) per run."""
    sisre_m: float = 0.5
    """Broadcast orbit and clock error along the line of sight: N(0, this^2) per satellite and run."""


@dataclass(frozen=True)
class RissGrade:
    """Reduced inertial sensors: vehicle CAN wheel speed and accelerometers, a MEMS yaw gyro."""

    wheel_scale_std: float = 0.005
    """Wheel speed scale factor error (tyre radius): N(0, this^2) per run."""
    wheel_noise_mps: float = 0.02
    accel_bias_mps2: float = 0.05
    accel_noise_mps2: float = 0.05
    gyro_bias_rad_s: float = math.radians(0.05)
    """Turn-on bias left after start-up calibration: N(0, this^2) per run."""
    gyro_instability_rad_s: float = math.radians(10.0 / 3600.0)
    """In-run bias instability (VG440CA-200: < 10 deg/h), first-order Gauss-Markov."""
    gyro_instability_tau_s: float = 300.0
    gyro_arw_rad_sqrt_s: float = math.radians(4.5) / 60.0
    """Angle random walk (VG440CA-200: 4.5 deg/sqrt(h))."""


@dataclass(frozen=True, eq=False)
class GnssScenario:
    """Everything a run needs except the random draws."""

    name: str
    site: tuple[float, float, float]
    """Site origin: latitude, longitude (rad), ellipsoidal height (m); x east, y north of its tangent
    plane."""
    gps_week: int
    start_tow_s: float
    segments: list[Segment]
    truth: Truth
    """Sampled at the RISS rate."""
    gnss_every: int
    """A GNSS epoch every this many RISS samples (the first sample is one)."""
    street: StreetView
    constellation: Constellation
    signal: SignalModel = field(default_factory=SignalModel)
    receiver: ReceiverModel = field(default_factory=ReceiverModel)
    riss: RissGrade = field(default_factory=RissGrade)
    urban: bool = True
    carrier: CarrierModel | None = field(default_factory=CarrierModel)
    """The carrier phase's lock, slips and errors (sim.gnss_carrier); None: pseudoranges without phase."""
    doppler: DopplerModel | None = field(default_factory=DopplerModel)
    """The Doppler's errors (sim.gnss_doppler), sent with the satellite's velocity and clock drift; None:
    pseudoranges without Doppler."""

    @property
    def riss_period(self) -> float:
        return float(self.truth.t[1] - self.truth.t[0])

    @property
    def gnss_samples(self) -> slice:
        """Truth samples that are GNSS epochs."""
        return slice(None, None, self.gnss_every)


def urban_scenario(
    *,
    short: bool = False,
    riss_rate_hz: float = 10.0,
    gnss_rate_hz: float = 1.0,
    heading0: float = START_HEADING,
) -> GnssScenario:
    """The Nanjing downtown drive (387 s; ``short``: about 70 s) in street canyons; ``heading0`` is the
    initial heading (rad, counter-clockwise from east)."""
    return _scenario("urban-nanjing", short, riss_rate_hz, gnss_rate_hz, CityParameters(), heading0=heading0)


def open_sky_scenario(
    *,
    short: bool = False,
    riss_rate_hz: float = 10.0,
    gnss_rate_hz: float = 1.0,
    heading0: float = START_HEADING,
) -> GnssScenario:
    """The same drive with no buildings and open-sky multipath: the check that the filters are sound."""
    signal = SignalModel(multipath_low_m=1.0, nlos_probability=0.0)
    return _scenario("open-sky-nanjing", short, riss_rate_hz, gnss_rate_hz, None, signal, heading0)


SCENARIOS = {"urban": urban_scenario, "open-sky": open_sky_scenario}


def _scenario(
    name: str,
    short: bool,
    riss_rate_hz: float,
    gnss_rate_hz: float,
    city: CityParameters | None,
    signal: SignalModel | None = None,
    heading0: float = START_HEADING,
) -> GnssScenario:
    every = round(riss_rate_hz / gnss_rate_hz)
    if every < 1 or not math.isclose(every * gnss_rate_hz, riss_rate_hz):
        raise ValueError("the RISS rate must be a whole multiple of the GNSS rate")
    segments = short_route() if short else nanjing_route()
    truth = drive(segments, 1.0 / riss_rate_hz, heading0=heading0)
    return GnssScenario(
        name=name + ("-short" if short else ""),
        site=NANJING_SITE,
        gps_week=GPS_WEEK,
        start_tow_s=START_TOW_S,
        segments=segments,
        truth=truth,
        gnss_every=every,
        street=street_view(truth, segments, city),
        constellation=gps_bds_constellation(GPS_WEEK * 604800.0 + START_TOW_S),
        signal=signal or SignalModel(),
        urban=city is not None,
    )
