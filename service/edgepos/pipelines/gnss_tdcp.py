"""Time-differenced carrier phase as the ``gnss_tight`` filters' motion (``carrier_smoothing`` tdcp or
hatch+tdcp; the displacement's math is gnss/tdcp.py).

Without RISS input the filters predict with a constant-velocity model whose white acceleration (3 m/s^2)
lets the position wander by metres between epochs, so each fix leans on its own epoch's code. The carrier
phases measure that step to centimetres: the position's motion becomes x_k = x_{k-1} + d + n, d the
displacement from the phase differences and n its error (the fit's covariance). That is an odometry input,
independent of the filter's state (the previous position enters only through the line of sight, at
sub-millimetre cost), so putting it into the prediction is exact for a Kalman filter where a measurement
of d against a cloned state would be the same update at more cost.

The filters (and the UPF's compiled step) propagate with the constant-velocity model, x + v dt. So the
cloud is first moved by x -> x + d - v dt per particle, its covariance by the same linear map T
(P -> T P T^T), and the model's process noise gets the displacement's covariance on the position and no
position-velocity cross term (:class:`DisplacementModel`): the constant-velocity step after that map is the
odometry step, F T = I on (position, velocity). The velocity keeps its random walk and its Doppler updates.
The displacement is in the state's north/east/up offsets with the local north/east/up rotation at the
previous position, and the map subtracts v dt in offsets where the constant-velocity step adds it with the
curvature at the particle (they differ by v dt times the height or latitude offset over the Earth's
radius: a 20 m step 30 m above the anchor, 0.1 mm).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import cast

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.kernels_base import FAILED, OK
from edgepos.core.measurements.gnss_geometry import delays as epoch_delays
from edgepos.core.measurements.gnss_kernel import anchor_array
from edgepos.core.motion import riss as layout
from edgepos.core.motion.riss import GnssOnlyModel
from edgepos.core.observations import Observation, PseudorangeObservation
from edgepos.core.particles import Cloud
from edgepos.gnss.geodesy import WGS84_A, WGS84_E2
from edgepos.gnss.measurements import Atmosphere, PseudorangeSet
from edgepos.gnss.orbits import OMEGA_EARTH, SPEED_OF_LIGHT
from edgepos.gnss.tdcp import (
    DEFAULT_GATE_PROBABILITY,
    MAX_CONDITION,
    MIN_SIN_ELEVATION,
    Displacement,
    PhaseHistory,
    TdcpConfig,
    bound,
    displacement,
    fit_rows,
    model_terms,
    slip_text,
    too_few,
)
from edgepos.pipelines.base import MeasurementUse
from edgepos.pipelines.gnss_satellites import EpochSatellites
from edgepos.pipelines.gnss_session import GnssSession
from edgepos.pipelines.gnss_tdcp_kernel import (
    TOO_FEW,
    displacement_kernel,
    fit_kernel,
    map_kernel,
    posterior_terms_kernel,
    shift_kernel,
)

TDCP_MODES = ("tdcp", "hatch+tdcp")
"""``carrier_smoothing`` values that use the phase differences as the filters' motion."""

_POSITION = [layout.NORTH, layout.EAST, layout.UP]
_VELOCITY = [layout.VN, layout.VE, layout.VU]
_BLOCK = np.ix_(_POSITION, _POSITION)
_CROSS = (np.array(_POSITION + _VELOCITY), np.array(_VELOCITY + _POSITION))
"""The position-velocity cross terms of Q, both triangles."""
_POSITION_FLOOR = 1e-6 * np.eye(3)
"""The constant-velocity model's floor on each position variance, kept (a millimetre)."""


@dataclass(frozen=True)
class DisplacementModel(GnssOnlyModel):
    """The GNSS-only model for a cloud moved by :func:`shift_cloud`: the same propagation (so every filter
    and the UPF's compiled step run it), its process noise with the displacement's covariance (north, east,
    up; row-major 3 x 3) on the position and no position-velocity cross terms."""

    displacement_cov: tuple[float, ...] = (0.0,) * 9
    _noise: dict[float, np.ndarray] = field(default_factory=dict, compare=False, repr=False)
    """Q per dt, built once (the pipeline's screens and the filter step each ask for it)."""

    def process_noise(self, dt: float) -> np.ndarray:
        q = self._noise.get(dt)
        if q is None:
            q = self.remember_noise(
                dt, super().process_noise(dt), np.array(self.displacement_cov).reshape(3, 3)
            )
        copy: np.ndarray = q.copy()
        return copy

    def remember_noise(self, dt: float, q: np.ndarray, displacement_cov: np.ndarray) -> np.ndarray:
        """Q over ``dt`` from the constant-velocity model's ``q`` (changed in place) and the displacement's
        covariance (the field's matrix: the caller that has it spares its rebuilding from the tuple)."""
        q[_CROSS] = 0.0
        q[_BLOCK] = displacement_cov + _POSITION_FLOOR
        self._noise[dt] = q
        return q


@dataclass(frozen=True)
class TdcpStep:
    """An epoch's phase differences: the model to predict with (None: the constant-velocity one, no
    displacement) and, per row of the epoch's pseudorange set, why its difference was not used (None: used;
    absent: no carrier phase)."""

    model: DisplacementModel | None
    reasons: dict[int, str | None]
    phases: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    """The rows' carrier phase, Doppler and LLI (:func:`_phases`), read once for the epoch."""


def enabled(options: dict[str, object]) -> bool:
    """Whether the session uses the phase differences (sessions stored before the option value: no)."""
    return options.get("carrier_smoothing", "off") in TDCP_MODES


def predict_with_displacement(
    session: GnssSession,
    t: float,
    dt: float,
    model: object,
    mean: np.ndarray,
    satellites: EpochSatellites,
    observations: Sequence[Observation],
    atmosphere: Atmosphere,
) -> TdcpStep:
    """Fit the displacement since the filter's previous epoch (``mean``: the cloud's mean there); when there
    is one (GNSS-only model, the phase history from that epoch), move ``session.cloud`` for it and return
    the model to predict with. The satellites' delays and elevations for the fit are taken at the previous
    fix, where the fit's model terms are (and not at the constant-velocity prediction, which the moved cloud
    replaces: so the epoch propagates its centre once; over one epoch's motion the delays change by
    fractions of a millimetre)."""
    phases = _phases(satellites, observations, session.options)
    carrying = np.flatnonzero(np.isfinite(phases[0])).tolist()
    if not isinstance(model, GnssOnlyModel) or session.anchor is None:
        return TdcpStep(None, dict.fromkeys(carrying, "the RISS input drives the motion this epoch"), phases)
    history = session.tdcp
    if history.receiver is None or history.t != session.filter_t:
        reasons: dict[int, str | None] = dict.fromkeys(
            carrying, "no carrier phase history at the filter's previous epoch"
        )
        return TdcpStep(None, reasons, phases)
    config = _config(
        session.options["tdcp_phase_std_m"],
        session.options["carrier_slip_cycles_per_s"],
        session.options["carrier_max_gap_s"],
    )
    prs = satellites.prs
    ionosphere_m, troposphere_m, elevation, _ = epoch_delays(atmosphere, np.array(history.receiver), prs)
    fit = epoch_displacement(history, t, prs, phases, (ionosphere_m, troposphere_m, elevation), config)
    reasons = {r: fit.reasons[r] for r in carrying}
    if fit.d is None or fit.cov is None:
        return TdcpStep(None, reasons, phases)
    lat, lon, _ = session.anchor.geodetic(mean)
    rotation = _north_east_up(float(lat), float(lon))
    step = rotation @ fit.d
    cov = rotation @ fit.cov @ rotation.T
    session.cloud = shift_cloud(session.cloud, step, dt)
    cov = 0.5 * (cov + cov.T)
    moved = DisplacementModel(
        model.anchor,
        model.accel_std,
        model.vertical_accel_std,
        model.clock_bias_psd,
        model.clock_drift_psd,
        tuple(cov.ravel().tolist()),
    )
    moved.remember_noise(dt, model.process_noise(dt), cov)
    return TdcpStep(moved, reasons, phases)


def epoch_displacement(
    history: PhaseHistory,
    t: float,
    prs: PseudorangeSet,
    phases: tuple[np.ndarray, np.ndarray, np.ndarray],
    delays: tuple[np.ndarray, np.ndarray, np.ndarray],
    config: TdcpConfig,
) -> Displacement:
    """``gnss.tdcp.displacement`` of the epoch's rows (``phases``: carrier, Doppler, LLI; ``delays``:
    ionosphere, troposphere, elevation) since ``history``'s epoch, whose position must be known. By the
    kernels (pipelines/gnss_tdcp_kernel.py), the numpy form when they are off: the same rows and reasons,
    the same differences to the bit, the fit's numbers to about 1e-12."""
    ionosphere_m, troposphere_m, elevation = delays
    cycles, doppler, lli = phases
    assert history.receiver is not None and history.t is not None
    receiver = np.array(history.receiver)
    wavelength = SPEED_OF_LIGHT / prs.frequency_hz
    if not compiled_enabled():
        terms = model_terms(
            receiver, prs.sat_position, prs.sat_clock_s, troposphere_m, ionosphere_m, SPEED_OF_LIGHT
        )
        return displacement(
            history, t, prs.sats, cycles, wavelength, prs.sat_position, terms, elevation, doppler, lli, config
        )
    n = len(cycles)
    std_all = config.phase_std_m / np.maximum(np.sin(elevation), MIN_SIN_ELEVATION)
    status, off, index = np.empty(n, dtype=np.int64), np.zeros(n), np.empty(n, dtype=np.int64)
    keep, left_out, solution, cov = (
        np.zeros(n, dtype=np.bool_),
        np.zeros((n, 2)),
        np.empty(4),
        np.empty((4, 4)),
    )
    dt = t - history.t
    constants = np.array(
        [OMEGA_EARTH, SPEED_OF_LIGHT, dt, config.max_gap_s, config.slip_cycles_per_s, MAX_CONDITION]
    )
    count, outcome = displacement_kernel(
        receiver,
        prs.sat_position,
        prs.sat_clock_s,
        troposphere_m,
        ionosphere_m,
        constants,
        cycles,
        history.table,
        history.rows(prs.sats),
        doppler,
        lli,
        wavelength,
        std_all,
        _bounds(config.gate_probability, n),
        config.min_satellites,
        status,
        off,
        index,
        keep,
        left_out,
        solution,
        cov,
    )
    reasons: list[str | None] = [None] * n
    for row in np.flatnonzero(status).tolist():  # the rows not differenced: few (most have no phase)
        reasons[row] = slip_text(int(status[row]), dt, float(off[row]), config)
    if outcome == TOO_FEW:
        return too_few(index[:count].tolist(), reasons, config)
    return _fit_outcome(index[:count], keep[:count], left_out[:count], outcome, solution, cov, reasons)


def compiled_fit(
    index: np.ndarray,
    y: np.ndarray,
    design: np.ndarray,
    std: np.ndarray,
    reasons: list[str | None],
    config: TdcpConfig,
) -> Displacement:
    """``gnss.tdcp.fit_rows`` by the kernel (pipelines/gnss_tdcp_kernel.py), the numpy form when the kernels
    are off: the same rows left out, the same reasons, the numbers to about 1e-12."""
    if not compiled_enabled():
        return fit_rows(index, y, design, std, reasons, config)
    n = len(index)
    keep = np.ones(n, dtype=np.bool_)
    solution, cov, left_out = np.empty(4), np.empty((4, 4)), np.zeros((n, 2))
    bounds = _bounds(config.gate_probability, n)
    status = fit_kernel(
        y, design, std, bounds, config.min_satellites, MAX_CONDITION, keep, solution, cov, left_out
    )
    return _fit_outcome(index, keep, left_out, status, solution, cov, reasons)


def _fit_outcome(
    index: np.ndarray,
    keep: np.ndarray,
    left_out: np.ndarray,
    status: int,
    solution: np.ndarray,
    cov: np.ndarray,
    reasons: list[str | None],
) -> Displacement:
    """The compiled fit's outputs as ``gnss.tdcp.fit_rows`` gives them: each row left out with its residual,
    the rows kept with None (a displacement) or why the epoch has none."""
    rows, kept = index.tolist(), keep.tolist()
    for r in np.flatnonzero(~keep).tolist():
        reasons[rows[r]] = (
            f"phase difference {left_out[r, 0]:+.2f} m off the displacement fit "
            f"({left_out[r, 1]:.1f} sigma; a slip or a reflection)"
        )
    if status == OK:
        for r, used in zip(rows, kept, strict=True):
            if used:
                reasons[r] = None
        return Displacement(solution[:3].copy(), cov[:3, :3].copy(), float(solution[3]), reasons, None)
    why, text = (
        ("singular geometry", "the satellites' geometry does not fix a displacement")
        if status == FAILED
        else (
            "inconsistent phase differences",
            "the epoch's phase differences are inconsistent (chi-square test)",
        )
    )
    for r, used in zip(rows, kept, strict=True):
        if used:
            reasons[r] = text
    return Displacement(None, None, 0.0, reasons, why)


@functools.lru_cache(maxsize=64)
def _bounds(probability: float, rows: int) -> np.ndarray:
    """The chi-square quantiles by degrees of freedom 0..rows (read-only), for the kernel."""
    table = np.array([bound(probability, dof) for dof in range(rows + 1)])
    table.flags.writeable = False
    return table


def shift_cloud(cloud: Cloud, step: np.ndarray, dt: float) -> Cloud:
    """The cloud moved by x -> x + step - v dt (position north/east/up, their velocities), its covariance
    by the same map, so that the constant-velocity step then gives x + step."""
    if compiled_enabled():
        particles = np.empty_like(cloud.particles)
        shift_kernel(cloud.particles, step, dt, particles)
    else:
        particles = cloud.particles.copy()
        # north, east, up are columns 0-2; their velocities v_north (4), v_east (3), v_up (5)
        particles[:, : layout.UP + 1] += step
        particles[:, : layout.EAST + 1] -= particles[:, layout.VN : layout.VE - 1 : -1] * dt
        particles[:, layout.UP] -= particles[:, layout.VU] * dt
    moved = Cloud(particles, cloud.log_weights, _mapped(cloud.cov, dt))
    known = cloud.known_moments(layout.ANGLES)
    if known is not None:  # the weighted moments of the moved particles, by the same linear map
        mean = known[0].copy()
        mean[_POSITION] += step - mean[_VELOCITY] * dt
        moved.remember_moments(layout.ANGLES, mean, _mapped(known[1], dt))
    return moved


def _mapped(cov: np.ndarray, dt: float) -> np.ndarray:
    """T C T^T for T = I with -dt from each velocity to its position, symmetric to the last bit: the
    position rows less dt times their velocity rows, then the same for the columns (``map_kernel`` when
    the kernels are on, the same bits)."""
    out = np.empty_like(cov)
    if compiled_enabled():
        map_kernel(cov, dt, out)
        return out
    out[...] = cov
    out[_POSITION, :] -= dt * cov[_VELOCITY, :]
    out[:, _POSITION] -= dt * out[:, _VELOCITY]
    symmetric: np.ndarray = 0.5 * (out + out.T)
    return symmetric


def remember_phases(
    session: GnssSession,
    t: float,
    satellites: EpochSatellites,
    step: TdcpStep,
    delays: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    posterior: np.ndarray,
) -> None:
    """Keep this epoch's phases (``step.phases``) and model terms at the filter's posterior position for the
    next epoch's differences (none when the epoch had no pseudorange with carrier phase)."""
    if session.anchor is None or delays is None or step.phases is None:
        session.tdcp = PhaseHistory()
        return
    ionosphere_m, troposphere_m, _ = delays
    cycles = step.phases[0]
    rows = np.flatnonzero(np.isfinite(cycles))
    if not rows.size:
        session.tdcp = PhaseHistory()
        return
    prs = satellites.prs
    if compiled_enabled():
        receiver, terms = np.empty(3), np.empty(len(cycles))
        posterior_terms_kernel(
            anchor_array(session.anchor),
            posterior,
            WGS84_A,
            WGS84_E2,
            prs.sat_position,
            prs.sat_clock_s,
            troposphere_m,
            ionosphere_m,
            OMEGA_EARTH,
            SPEED_OF_LIGHT,
            receiver,
            terms,
        )
    else:
        receiver = session.anchor.ecef(posterior)
        terms = model_terms(
            receiver, prs.sat_position, prs.sat_clock_s, troposphere_m, ionosphere_m, SPEED_OF_LIGHT
        )
    x, y, z = receiver.tolist()
    sats = prs.sats
    table = np.empty((rows.size, 2))
    table[:, 0], table[:, 1] = cycles[rows], terms[rows]
    session.tdcp = PhaseHistory(t, (x, y, z), [sats[r] for r in rows.tolist()], table)


def report(
    uses: dict[int, MeasurementUse],
    noise: dict[int, tuple[float, str]],
    indices: Sequence[int],
    step: TdcpStep,
) -> None:
    """Say in each pseudorange's report whether its phase difference entered the displacement: for a used
    row in its noise reason (``noise``, before the reports are made from it: no report copied), for a row
    left out in its report's reason."""
    for row, why in step.reasons.items():
        i = indices[row]
        note = (
            "phase difference used for the displacement"
            if why is None
            else f"phase difference not used: {why}"
        )
        if step.model is None and why is None:
            note = "phase difference not used: the epoch gave no displacement"
        noted = noise.get(i)
        if noted is not None:
            noise[i] = (noted[0], f"{noted[1]}; {note}")
            continue
        use = uses.get(i)
        if use is not None:
            uses[i] = _replace(use, reason=note if use.reason is None else f"{use.reason}; {note}")


def _replace(use: MeasurementUse, **changes: object) -> MeasurementUse:
    copy = object.__new__(MeasurementUse)
    copy.__dict__.update(use.__dict__)
    copy.__dict__.update(changes)
    return copy


def _phases(
    satellites: EpochSatellites, observations: Sequence[Observation], options: dict[str, object]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of the epoch's set: carrier phase (NaN: none), Doppler (NaN: none or unused) and LLI."""
    sent = [cast(PseudorangeObservation, observations[i]) for i in satellites.indices]
    use_doppler = bool(options.get("use_doppler", True))
    cycles = np.array([math.nan if o.carrier_cycles is None else o.carrier_cycles for o in sent], dtype=float)
    doppler = np.array(
        [o.doppler_hz if (o.doppler_hz is not None and use_doppler) else math.nan for o in sent], dtype=float
    )
    lli = np.array([o.lli or 0 for o in sent], dtype=int)
    return cycles, doppler, lli


@functools.lru_cache(maxsize=64)
def _config(phase_std_m: float, slip_cycles_per_s: float, max_gap_s: float) -> TdcpConfig:
    """The fit's settings from the session's options (built once per distinct set)."""
    return TdcpConfig(
        float(phase_std_m),
        DEFAULT_GATE_PROBABILITY,
        slip_cycles_per_s=float(slip_cycles_per_s),
        max_gap_s=float(max_gap_s),
    )


def _north_east_up(lat: float, lon: float) -> np.ndarray:
    """Rows: the local north, east and up unit vectors (ECEF) at a latitude and longitude (rad), the state's
    position order."""
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-sl * co, -sl * so, cl], [-so, co, 0.0], [cl * co, cl * so, sl]])
