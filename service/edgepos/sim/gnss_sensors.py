"""Simulated GPS/BeiDou pseudoranges and RISS samples of a :class:`GnssScenario`.

Pseudorange of satellite j at a GNSS epoch (receive time t, true GPS time):

    P = |Rz(omega_e tau) s_j(t - tau) - r(t)| + b_sys(t) - c dts_j(t - tau)
        + I_j + T_j + e_sisre,j + m_j(t) + n_j(t) + nlos_j(t)

with s_j the satellite's ECEF position at transmit time (tau found by iteration, so the Earth-rotation
term is the exact rotation, which the receiver's Sagnac correction models), b_sys the receiver clock bias
of the constellation (GPS bias + inter-system bias for BeiDou; integrated random walk of bias and drift),
dts_j the satellite clock (sent as ``sat_clock``, with ``sat_position`` = s_j), I the ionosphere left after
a broadcast correction, T the true troposphere (Saastamoinen x a per-run factor), e_sisre the broadcast
orbit/clock error, m the LOS multipath (Gauss-Markov, larger at low elevation), n the code noise (from
C/N0) and nlos the extra path of a reflected signal. A satellite is tracked when it is above the horizon
mask and either above the street-canyon cut-off (LOS) or received by reflection (NLOS), and its C/N0 is
above the tracking threshold. The carrier phase of a signal the carrier loop holds in lock goes with it
(``sim.gnss_carrier``: lock and slips at the rates of the real recording), and so does its Doppler with
the satellite's velocity and clock drift (``sim.gnss_doppler``: noise by C/N0 as on the real recording).

RISS samples at every truth sample: wheel speed (scale error + noise), forward and lateral specific force
(bias + noise; the road is level, so they are the longitudinal acceleration and speed x yaw rate), yaw
gyro (turn-on bias + Gauss-Markov instability + angle random walk).

All random numbers are drawn up front in a fixed order from the caller's generator, whatever is visible,
so a run depends only on its seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from edgepos.core.observations import Observation, PseudorangeObservation, RissObservation
from edgepos.gnss.corrections import saastamoinen_delay
from edgepos.gnss.geodesy import enu_rotation, geodetic_to_ecef
from edgepos.gnss.orbits import OMEGA_EARTH, SPEED_OF_LIGHT
from edgepos.sim.gnss_carrier import carrier_phase, draw
from edgepos.sim.gnss_doppler import noise_std, path_rate, range_rate
from edgepos.sim.gnss_scenario import GnssScenario, ReceiverModel
from edgepos.sim.urban import ANTENNA_HEIGHT_M, StreetView

#: Carrier frequencies of the simulated signals: GPS L1 C/A, BeiDou B1I.
FREQUENCY_HZ = {"G": 1575.42e6, "C": 1561.098e6}


@dataclass(frozen=True, eq=False)
class GnssRun:
    """One simulated run: the observation stream (epochs in time order) and what it was made of."""

    epochs: list[list[Observation]]
    """One list per RISS sample; GNSS epochs also carry that epoch's pseudoranges."""
    gnss_tow: np.ndarray
    """(K,) GPS time of week of the GNSS epochs."""
    truth_east: np.ndarray
    truth_north: np.ndarray
    """(K,) true antenna position in the site frame (m)."""
    elevation: np.ndarray
    azimuth: np.ndarray
    """(K, n) true elevation and azimuth (rad, azimuth clockwise from north)."""
    cutoff: np.ndarray
    """(K, n) street-canyon cut-off elevation (rad)."""
    los: np.ndarray
    nlos: np.ndarray
    """(K, n) tracked in line of sight / tracked by reflection only."""
    cn0: np.ndarray
    error: np.ndarray
    """(K, n) C/N0 (dB-Hz) and pseudorange error (m) beyond geometry, clocks and modelled troposphere."""

    @property
    def observations(self) -> list[Observation]:
        """All epochs flattened, as one batch."""
        return [observation for epoch in self.epochs for observation in epoch]


def _gauss_markov(innovations: np.ndarray, step: float, tau: float) -> np.ndarray:
    """Unit-variance first-order Gauss-Markov series along axis 0 from standard normal ``innovations``."""
    phi = math.exp(-step / tau)
    scale = math.sqrt(1.0 - phi * phi)
    out = np.empty_like(innovations)
    out[0] = innovations[0]
    for k in range(1, len(innovations)):
        out[k] = phi * out[k - 1] + scale * innovations[k]
    return out


def klobuchar_obliquity(elevation: np.ndarray) -> np.ndarray:
    """Klobuchar's slant factor F = 1 + 16 (0.53 - E)^3, E the elevation in semicircles."""
    result: np.ndarray = 1.0 + 16.0 * (0.53 - np.maximum(elevation, 0.0) / math.pi) ** 3
    return result


def simulate(scenario: GnssScenario, rng: np.random.Generator) -> GnssRun:
    """Draw one run of the scenario's measurements."""
    truth, constellation = scenario.truth, scenario.constellation
    signal, receiver, grade = scenario.signal, scenario.receiver, scenario.riss
    rows = np.arange(truth.t.size)[scenario.gnss_samples]
    epochs_count, sats = rows.size, len(constellation)
    gnss_step = scenario.gnss_every * scenario.riss_period
    places = int(scenario.street.place.max()) + 1

    # -- every random number, in a fixed order ------------------------------------------------------
    clock_bias0 = rng.uniform(-receiver.clock_bias_range_m, receiver.clock_bias_range_m)
    inter_system = rng.normal(0.0, receiver.inter_system_bias_m)
    drift0 = rng.normal(0.0, receiver.clock_drift_std_mps)
    clock_walk = rng.standard_normal((epochs_count, 2))
    iono_vertical = rng.normal(0.0, receiver.iono_vertical_residual_m)
    iono_satellite = rng.normal(0.0, receiver.iono_satellite_m, sats)
    tropo_factor = 1.0 + rng.normal(0.0, receiver.tropo_fraction)
    sisre = rng.normal(0.0, receiver.sisre_m, sats)
    nlos_draw = rng.uniform(size=(places, sats))
    nlos_loss = rng.uniform(*signal.nlos_loss_db, (places, sats))
    nlos_extra = rng.uniform(*signal.nlos_extra_m, (places, sats))
    multipath_innovations = rng.standard_normal((epochs_count, sats))
    cn0_innovations = rng.standard_normal((epochs_count, sats))
    code_noise = rng.standard_normal((epochs_count, sats))
    cn0_white = rng.standard_normal((epochs_count, sats))
    samples = truth.t.size
    wheel_scale = rng.normal(0.0, grade.wheel_scale_std)
    accel_bias = rng.normal(0.0, grade.accel_bias_mps2, 2)
    gyro_bias = rng.normal(0.0, grade.gyro_bias_rad_s)
    riss_noise = rng.standard_normal((samples, 4))
    gyro_instability = rng.standard_normal(samples)
    carrier_draws = None if scenario.carrier is None else draw(rng, (epochs_count, sats), scenario.carrier)
    doppler_noise = None if scenario.doppler is None else rng.standard_normal((epochs_count, sats))

    # -- receiver positions and satellite geometry --------------------------------------------------
    lat0, lon0, h0 = scenario.site
    origin = geodetic_to_ecef(lat0, lon0, h0)
    enu = np.stack([truth.x[rows], truth.y[rows], np.full(epochs_count, ANTENNA_HEIGHT_M)], axis=-1)
    receiver_ecef = enu @ enu_rotation(lat0, lon0) + origin
    week_start = scenario.gps_week * 604800.0
    tow = scenario.start_tow_s + truth.t[rows]
    gpst = week_start + tow
    tau = np.full((epochs_count, sats), 0.075)
    for _ in range(4):
        transmit = constellation.ecef_each(gpst[:, None] - tau)
        rotated = _rotate(transmit, tau)
        distance = np.linalg.norm(rotated - receiver_ecef[:, None, :], axis=-1)
        tau = distance / SPEED_OF_LIGHT
    transmit = constellation.ecef_each(gpst[:, None] - tau)
    line = _rotate(transmit, tau) - receiver_ecef[:, None, :]
    geometric = np.linalg.norm(line, axis=-1)
    local = line @ enu_rotation(lat0, lon0).T
    elevation = np.arctan2(local[..., 2], np.hypot(local[..., 0], local[..., 1]))
    azimuth = np.mod(np.arctan2(local[..., 0], local[..., 1]), 2.0 * math.pi)

    # -- visibility, C/N0 and errors ---------------------------------------------------------------
    view = scenario.street
    street_rows = _take_view(view, rows)
    cutoff = street_rows.cutoff(azimuth)
    above_horizon = elevation >= signal.horizon_mask_rad
    line_of_sight = above_horizon & (elevation >= cutoff)
    place = street_rows.place[:, None]
    columns = np.arange(sats)[None, :]
    reflected = above_horizon & ~line_of_sight & (nlos_draw[place, columns] < signal.nlos_probability)

    weak = np.array([kind != "MEO" for kind in constellation.kinds])
    cn0 = (
        signal.cn0_horizon_dbhz
        + (signal.cn0_zenith_dbhz - signal.cn0_horizon_dbhz) * np.sin(np.maximum(elevation, 0.0))
        - signal.cn0_geo_loss_db * weak
        + signal.cn0_walk_db * _gauss_markov(cn0_innovations, gnss_step, signal.cn0_walk_tau_s)
        + signal.cn0_white_db * cn0_white
        - np.where(reflected, nlos_loss[place, columns], 0.0)
    )
    tracked = (line_of_sight | reflected) & (cn0 >= signal.tracking_threshold_dbhz)
    multipath_std = signal.multipath_floor_m + signal.multipath_low_m * np.exp(
        -np.maximum(elevation, 0.0) / signal.multipath_scale_rad
    )
    multipath_unit = _gauss_markov(multipath_innovations, gnss_step, signal.multipath_tau_s)
    multipath = multipath_std * multipath_unit
    noise = signal.code_noise_m * 10.0 ** ((45.0 - cn0) / 20.0) * code_noise
    reflector = street_rows.facade_distance_opposite(azimuth)
    relative = azimuth - street_rows.axis[:, None]
    specular = 2.0 * reflector * np.cos(elevation) * np.abs(np.sin(relative))
    extra = np.where(reflected, specular + nlos_extra[place, columns], 0.0)

    frequency = np.array([FREQUENCY_HZ[system] for system in constellation.systems])
    iono = (
        (iono_vertical + iono_satellite)
        * klobuchar_obliquity(elevation)
        * (FREQUENCY_HZ["G"] / frequency) ** 2
    )
    tropo = tropo_factor * saastamoinen_delay(lat0, h0 + ANTENNA_HEIGHT_M, elevation)
    error = iono + (tropo_factor - 1.0) / tropo_factor * tropo + sisre + multipath + noise + extra

    bias, drift = _receiver_clock(clock_bias0, drift0, clock_walk, gnss_step, receiver)
    is_beidou = np.array([system == "C" for system in constellation.systems])
    receiver_bias = bias[:, None] + inter_system * is_beidou[None, :]
    sat_clock = constellation.clock(gpst[:, None] - tau)
    pseudorange = (
        geometric
        + receiver_bias
        - SPEED_OF_LIGHT * sat_clock
        + iono
        + tropo
        + sisre
        + multipath
        + noise
        + extra
    )
    phase = None
    if scenario.carrier is not None and carrier_draws is not None:
        phase_path = geometric + receiver_bias - SPEED_OF_LIGHT * sat_clock - iono + tropo + sisre + extra
        phase = carrier_phase(
            carrier_draws, scenario.carrier, tracked, cn0, phase_path, multipath_unit, frequency
        )

    doppler = sat_velocity = None
    if scenario.doppler is not None and doppler_noise is not None:
        sat_velocity = constellation.ecef_velocity_each(gpst[:, None] - tau)
        heading = truth.heading[rows]
        enu_velocity = np.stack(
            [
                truth.speed[rows] * np.cos(heading),
                truth.speed[rows] * np.sin(heading),
                np.zeros(epochs_count),
            ],
            axis=-1,
        )
        reflected_rate = (
            np.where(reflected, path_rate(specular, street_rows.place, gnss_step), 0.0)
            if scenario.doppler.reflected_rate
            else np.zeros_like(specular)
        )
        rate = range_rate(
            line,
            _rotate(sat_velocity, tau),
            enu_velocity @ enu_rotation(lat0, lon0),
            drift,
            constellation.clock_drift,
            reflected_rate,
        )
        rate = rate + scenario.doppler.noise_scale * noise_std(cn0) * doppler_noise
        doppler = -rate * frequency[None, :] / SPEED_OF_LIGHT

    # -- RISS ---------------------------------------------------------------------------------------
    dt = scenario.riss_period
    cos_h, sin_h = np.cos(truth.heading), np.sin(truth.heading)
    longitudinal = truth.ax * cos_h + truth.ay * sin_h
    lateral = -truth.ax * sin_h + truth.ay * cos_h
    wheel = np.maximum(truth.speed * (1.0 + wheel_scale) + grade.wheel_noise_mps * riss_noise[:, 0], 0.0)
    accel_x = longitudinal + accel_bias[0] + grade.accel_noise_mps2 * riss_noise[:, 1]
    accel_y = lateral + accel_bias[1] + grade.accel_noise_mps2 * riss_noise[:, 2]
    instability = grade.gyro_instability_rad_s * _gauss_markov(
        gyro_instability, dt, grade.gyro_instability_tau_s
    )
    gyro_white = grade.gyro_arw_rad_sqrt_s / math.sqrt(dt)
    gyro = truth.yaw_rate + gyro_bias + instability + gyro_white * riss_noise[:, 3]

    names = constellation.systems
    prns = constellation.prns.tolist()
    epochs: list[list[Observation]] = []
    gnss_index = {int(row): k for k, row in enumerate(rows)}
    riss_tow = scenario.start_tow_s + truth.t
    for sample in range(samples):
        t = float(riss_tow[sample])
        epoch: list[Observation] = [
            RissObservation(
                t=t,
                wheel_speed=float(wheel[sample]),
                accel_x=float(accel_x[sample]),
                accel_y=float(accel_y[sample]),
                gyro_z=float(gyro[sample]),
            )
        ]
        k = gnss_index.get(sample)
        if k is not None:
            t = float(tow[k])
            for j in np.flatnonzero(tracked[k]):
                epoch.append(
                    PseudorangeObservation(
                        t=t,
                        system=names[j],
                        prn=int(prns[j]),
                        pseudorange=float(pseudorange[k, j]),
                        cn0=float(round(cn0[k, j], 2)),
                        sat_position=(
                            float(transmit[k, j, 0]),
                            float(transmit[k, j, 1]),
                            float(transmit[k, j, 2]),
                        ),
                        sat_clock=float(sat_clock[k, j]),
                        carrier_cycles=None if phase is None else _finite_or_none(phase.cycles[k, j]),
                        lli=None if phase is None or math.isnan(phase.cycles[k, j]) else int(phase.lli[k, j]),
                        doppler_hz=None if doppler is None else float(doppler[k, j]),
                        sat_velocity=None if sat_velocity is None else _triple(sat_velocity[k, j]),
                        sat_clock_drift=None if sat_velocity is None else float(constellation.clock_drift[j]),
                    )
                )
        epochs.append(epoch)
    return GnssRun(
        epochs=epochs,
        gnss_tow=tow,
        truth_east=truth.x[rows].copy(),
        truth_north=truth.y[rows].copy(),
        elevation=elevation,
        azimuth=azimuth,
        cutoff=cutoff,
        los=tracked & line_of_sight,
        nlos=tracked & ~line_of_sight,
        cn0=cn0,
        error=np.where(tracked, error, np.nan),
    )


def _triple(vector: np.ndarray) -> tuple[float, float, float]:
    return (float(vector[0]), float(vector[1]), float(vector[2]))


def _finite_or_none(value: float) -> float | None:
    return None if math.isnan(value) else float(value)


def _rotate(position: np.ndarray, travel_time: np.ndarray) -> np.ndarray:
    """ECEF positions of the transmit epoch expressed in the ECEF frame ``travel_time`` seconds later."""
    angle = OMEGA_EARTH * travel_time
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = position[..., 0], position[..., 1], position[..., 2]
    return np.stack([c * x + s * y, -s * x + c * y, z], axis=-1)


def _take_view(view: StreetView, rows: np.ndarray) -> StreetView:
    """The street view at the truth samples ``rows``."""
    return StreetView(
        *(
            getattr(view, name)[rows]
            for name in ("axis", "left", "right", "left_height", "right_height", "open_cross", "place")
        )
    )


def _receiver_clock(
    bias0: float, drift0: float, walk: np.ndarray, step: float, model: ReceiverModel
) -> tuple[np.ndarray, np.ndarray]:
    """Bias (m) and drift (m/s) at the GNSS epochs: the exact discretisation of the two-state clock
    (integrated random walks with densities ``clock_bias_psd`` and ``clock_drift_psd``)."""
    q_bias, q_drift = model.clock_bias_psd, model.clock_drift_psd
    q = np.array(
        [
            [q_bias * step + q_drift * step**3 / 3.0, q_drift * step**2 / 2.0],
            [q_drift * step**2 / 2.0, q_drift * step],
        ]
    )
    factor = np.linalg.cholesky(q)
    bias, drift = np.empty(len(walk)), np.empty(len(walk))
    bias[0], drift[0] = bias0, drift0
    for k in range(1, len(walk)):
        increment = factor @ walk[k]
        bias[k] = bias[k - 1] + drift[k - 1] * step + increment[0]
        drift[k] = drift[k - 1] + increment[1]
    return bias, drift
