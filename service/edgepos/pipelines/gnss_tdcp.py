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

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.kernels_base import FAILED, OK
from edgepos.core.measurements.gnss_geometry import delays as epoch_delays
from edgepos.core.measurements.gnss_kernel import anchor_array
from edgepos.core.motion import riss as layout
from edgepos.core.motion.riss import GeodeticAnchor, GnssOnlyModel
from edgepos.core.observations import Observation
from edgepos.core.particles import Cloud
from edgepos.gnss.geodesy import WGS84_A, WGS84_E2
from edgepos.gnss.measurements import Atmosphere, PseudorangeSet
from edgepos.gnss.orbits import OMEGA_EARTH, SPEED_OF_LIGHT
from edgepos.gnss.tdcp import (
    DEFAULT_GATE_PROBABILITY,
    GAP,
    MAX_CONDITION,
    MIN_SIN_ELEVATION,
    NO_PHASE,
    SLIP,
    Displacement,
    PhaseHistory,
    TdcpConfig,
    bound,
    displacement,
    model_terms,
    slip_text,
)
from edgepos.pipelines.base import MeasurementUse
from edgepos.pipelines.gnss_satellites import EpochSatellites, epoch_phases
from edgepos.pipelines.gnss_session import GnssSession
from edgepos.pipelines.gnss_tdcp_kernel import (
    FEW,
    INCONSISTENT,
    LEFT_OUT,
    TOO_FEW,
    epoch_kernel,
    posterior_terms_kernel,
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
            cov = np.array(self.displacement_cov).reshape(3, 3)
            q = self.remember_noise(dt, displacement_noise(super().process_noise(dt), cov))
        copy: np.ndarray = q.copy()
        return copy

    def remember_noise(self, dt: float, q: np.ndarray) -> np.ndarray:
        """Keep ``q`` as Q over ``dt`` (:func:`displacement_noise` of this model's covariance: a caller that
        has it built spares its rebuilding from the tuple)."""
        self._noise[dt] = q
        return q


def displacement_noise(q: np.ndarray, displacement_cov: np.ndarray) -> np.ndarray:
    """:class:`DisplacementModel`'s Q from the constant-velocity model's ``q`` (changed in place) and the
    displacement's covariance (north, east, up): no position-velocity cross terms, the position block the
    displacement's with the constant-velocity model's floor."""
    q[_CROSS] = 0.0
    q[_BLOCK] = displacement_cov + _POSITION_FLOOR
    return q


@dataclass(frozen=True)
class TdcpStep:
    """An epoch's phase differences: the model to predict with (None: the constant-velocity one, no
    displacement) and, per row of the epoch's pseudorange set, why its difference was not used (None: used;
    absent: no carrier phase)."""

    model: DisplacementModel | None
    reasons: dict[int, str | None]
    phases: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    """The rows' carrier phase, Doppler and LLI (``gnss_satellites.epoch_phases``), read once for the epoch."""
    anchor: np.ndarray | None = None
    """The session's anchor as ``gnss_kernel.anchor_array`` gives it, built once for the epoch."""


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
    fractions of a millimetre). By one kernel (:func:`compiled_step`), or :func:`reference_step`."""
    phases = satellites.phases
    if phases is None:  # carrier smoothing off (tdcp alone) or without phases this epoch
        phases = epoch_phases(satellites, observations, session.options)
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
    anchor = anchor_numbers(session.anchor)
    run = compiled_step if compiled_enabled() else reference_step
    q = model.process_noise(dt)
    fit, cloud, noise = run(
        history, t, satellites.prs, phases, atmosphere, config, anchor, mean, session.cloud, q
    )
    reasons = {r: fit.reasons[r] for r in carrying}
    if cloud is None or noise is None:
        return TdcpStep(None, reasons, phases, anchor)
    session.cloud = cloud
    moved = DisplacementModel(
        model.anchor,
        model.accel_std,
        model.vertical_accel_std,
        model.clock_bias_psd,
        model.clock_drift_psd,
        tuple(noise.ravel().tolist()),
    )
    moved.remember_noise(dt, q)
    return TdcpStep(moved, reasons, phases, anchor)


Moved = tuple[Displacement, Cloud | None, np.ndarray | None]
"""An epoch's displacement step: the fit, and when it gave a displacement the moved cloud and the
displacement's covariance in north/east/up (the displacement model's position noise; the step has then
made its ``q`` argument :func:`displacement_noise` of it); else None, None."""


def reference_step(
    history: PhaseHistory,
    t: float,
    prs: PseudorangeSet,
    phases: tuple[np.ndarray, np.ndarray, np.ndarray],
    atmosphere: Atmosphere,
    config: TdcpConfig,
    anchor: np.ndarray,
    mean: np.ndarray,
    cloud: Cloud,
    q: np.ndarray,
) -> Moved:
    """The displacement step in numpy (``EDGEPOS_NUMBA=0``, and the reference the kernel is held to): the
    delays at the previous fix, ``gnss.tdcp.displacement`` of the epoch's rows (``phases``: carrier,
    Doppler, LLI), its rotation to north/east/up at ``mean`` (:func:`rotated`) and :func:`shift_cloud`."""
    assert history.receiver is not None and history.t is not None
    receiver = np.array(history.receiver)
    ionosphere_m, troposphere_m, elevation, _ = epoch_delays(atmosphere, receiver, prs)
    terms = model_terms(
        receiver, prs.sat_position, prs.sat_clock_s, troposphere_m, ionosphere_m, SPEED_OF_LIGHT
    )
    cycles, doppler, lli = phases
    wavelength = SPEED_OF_LIGHT / prs.frequency_hz
    fit = displacement(
        history, t, prs.sats, cycles, wavelength, prs.sat_position, terms, elevation, doppler, lli, config
    )
    if fit.d is None or fit.cov is None:
        return fit, None, None
    # GeodeticAnchor.geodetic of the mean, from the anchor's numbers as the kernels take them
    lat = float(anchor[0] + mean[layout.NORTH] / anchor[3])
    lon = float(anchor[1] + mean[layout.EAST] / anchor[4])
    step, noise = rotated(north_east_up(lat, lon), fit.d, fit.cov)
    displacement_noise(q, noise)
    return fit, shift_cloud(cloud, step, t - history.t), noise


def rotated(rotation: np.ndarray, d: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``rotation`` @ ``d`` and ``rotation`` @ ``cov`` @ ``rotation``.T made symmetric, each sum over the
    three terms in index order (BLAS's 3 x 3 products round as its kernel for the CPU does: this order is
    the kernel's on every machine)."""
    step = (rotation[:, 0] * d[0] + rotation[:, 1] * d[1]) + rotation[:, 2] * d[2]
    left = (rotation[:, 0:1] * cov[0] + rotation[:, 1:2] * cov[1]) + rotation[:, 2:3] * cov[2]
    both = (left[:, 0:1] * rotation[:, 0] + left[:, 1:2] * rotation[:, 1]) + left[:, 2:3] * rotation[:, 2]
    symmetric: np.ndarray = 0.5 * (both + both.T)
    return step, symmetric


_NO_MOMENTS = (np.zeros(0), np.zeros((0, 0)))
"""``move_kernel``'s moments for a cloud without remembered ones (it maps none)."""


def compiled_step(
    history: PhaseHistory,
    t: float,
    prs: PseudorangeSet,
    phases: tuple[np.ndarray, np.ndarray, np.ndarray],
    atmosphere: Atmosphere,
    config: TdcpConfig,
    anchor: np.ndarray,
    mean: np.ndarray,
    cloud: Cloud,
    q: np.ndarray,
) -> Moved:
    """:func:`reference_step` by ``epoch_kernel`` (pipelines/gnss_tdcp_kernel.py), one call: the same rows
    and reasons, the differences to the bit, the fit's numbers to about 1e-12 (its rounding), and from the
    fit on the rotation, noise and move to the bit."""
    assert history.receiver is not None and history.t is not None
    n = len(prs)
    cycles, doppler, lli = phases
    klobuchar = np.zeros(8)
    if atmosphere.klobuchar is not None:
        klobuchar[:4], klobuchar[4:] = atmosphere.klobuchar
    dt = t - history.t
    constants = np.array(
        [
            OMEGA_EARTH,
            SPEED_OF_LIGHT,
            dt,
            config.max_gap_s,
            config.slip_cycles_per_s,
            MAX_CONDITION,
            config.phase_std_m,
            MIN_SIN_ELEVATION,
            float(prs.gpst),
            config.min_satellites,
            float(atmosphere.klobuchar is not None),
            float(atmosphere.troposphere),
            _POSITION_FLOOR[0, 0],
        ]
    )
    status, values = np.empty(n, dtype=np.int64), np.empty((n, 2))
    solution, fit_cov, noise = np.empty(4), np.empty((4, 4)), np.empty((3, 3))
    known = cloud.known_moments(layout.ANGLES)
    moments_mean, moments_cov = _NO_MOMENTS if known is None else known
    particles, cov = np.empty_like(cloud.particles), np.empty_like(cloud.cov)
    out_mean, out_moments_cov = np.empty_like(moments_mean), np.empty_like(moments_cov)
    count, outcome = epoch_kernel(
        np.array(history.receiver),
        prs.sat_position,
        prs.frequency_hz,
        prs.sat_clock_s,
        klobuchar,
        constants,
        cycles,
        history.table,
        history.rows(prs.sats),
        doppler,
        lli,
        bounds_table(config.gate_probability, n),
        anchor,
        mean,
        cloud.particles,
        cloud.cov,
        moments_mean,
        moments_cov,
        status,
        values,
        solution,
        fit_cov,
        noise,
        q,
        particles,
        cov,
        out_mean,
        out_moments_cov,
    )
    codes = status.tolist()
    reasons: list[str | None] = [_ROW_TEXT[code] for code in codes]
    for row, code in enumerate(codes):
        if code in _NUMBERED:
            reasons[row] = _numbered_text(code, values[row], dt, count, config)
    if outcome != OK:
        return (
            Displacement(None, None, 0.0, reasons, _NO_FIT[outcome] or f"{count} continuous carrier phases"),
            None,
            None,
        )
    fit = Displacement(solution[:3], fit_cov[:3, :3], float(solution[3]), reasons, None)
    moved = Cloud(particles, cloud.log_weights, cov)
    if known is not None:
        moved.remember_moments(layout.ANGLES, out_mean, out_moments_cov)
    return fit, moved, noise


_GEOMETRY = "the satellites' geometry does not fix a displacement"
_INCONSISTENT = "the epoch's phase differences are inconsistent (chi-square test)"
_ROW_TEXT: tuple[str | None, ...] = (
    *(slip_text(code, 0.0, 0.0, TdcpConfig()) for code in range(NO_PHASE + 1)),
    None,
    _GEOMETRY,
    _INCONSISTENT,
    None,
)
"""``epoch_kernel``'s row codes worded as ``gnss.tdcp`` words them, where the words carry no number."""
_NUMBERED = frozenset((GAP, SLIP, LEFT_OUT, FEW))
_NO_FIT = {FAILED: "singular geometry", INCONSISTENT: "inconsistent phase differences", TOO_FEW: None}
"""The epoch's ``Displacement.why`` by the kernel's outcome (TOO_FEW: worded with the count)."""


def _numbered_text(code: int, values: np.ndarray, dt: float, count: int, config: TdcpConfig) -> str | None:
    """A row's reason that carries numbers, as ``gnss.tdcp`` words it (``displacement``, ``fit_rows``,
    ``too_few``)."""
    if code == LEFT_OUT:
        return (
            f"phase difference {values[0]:+.2f} m off the displacement fit "
            f"({values[1]:.1f} sigma; a slip or a reflection)"
        )
    if code == FEW:
        return f"{count} continuous phases, fewer than {config.min_satellites}"
    return slip_text(code, dt, float(values[0]), config)


@functools.lru_cache(maxsize=64)
def bounds_table(probability: float, rows: int) -> np.ndarray:
    """The chi-square quantiles by degrees of freedom 0..rows (read-only), for the kernel."""
    table = np.array([bound(probability, dof) for dof in range(rows + 1)])
    table.flags.writeable = False
    return table


def shift_cloud(cloud: Cloud, step: np.ndarray, dt: float) -> Cloud:
    """The cloud moved by x -> x + step - v dt (position north/east/up, their velocities), its covariance
    by the same map, so that the constant-velocity step then gives x + step (numpy; ``move_kernel`` in
    :func:`compiled_step`, the same bits)."""
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
    position rows less dt times their velocity rows, then the same for the columns (the numpy form of
    ``move_kernel``'s ``map_kernel``, the same bits)."""
    out = cov.copy()
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
    prs, n = satellites.prs, len(cycles)
    if compiled_enabled():
        receiver, table, index = np.empty(3), np.empty((n, 2)), np.empty(n, dtype=np.int64)
        count = posterior_terms_kernel(
            anchor_numbers(session.anchor) if step.anchor is None else step.anchor,
            posterior,
            WGS84_A,
            WGS84_E2,
            prs.sat_position,
            prs.sat_clock_s,
            troposphere_m,
            ionosphere_m,
            OMEGA_EARTH,
            SPEED_OF_LIGHT,
            cycles,
            receiver,
            table,
            index,
        )
        rows: list[int] = index[:count].tolist()
        table = table[:count]
    else:
        receiver = session.anchor.ecef(posterior)
        terms = model_terms(
            receiver, prs.sat_position, prs.sat_clock_s, troposphere_m, ionosphere_m, SPEED_OF_LIGHT
        )
        rows = np.flatnonzero(np.isfinite(cycles)).tolist()
        table = np.empty((len(rows), 2))
        table[:, 0], table[:, 1] = cycles[rows], terms[rows]
    if not rows:
        session.tdcp = PhaseHistory()
        return
    x, y, z = receiver.tolist()
    sats = prs.sats
    session.tdcp = PhaseHistory(t, (x, y, z), [sats[r] for r in rows], table)


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


@functools.lru_cache(maxsize=64)
def _config(phase_std_m: float, slip_cycles_per_s: float, max_gap_s: float) -> TdcpConfig:
    """The fit's settings from the session's options (built once per distinct set)."""
    return TdcpConfig(
        float(phase_std_m),
        DEFAULT_GATE_PROBABILITY,
        slip_cycles_per_s=float(slip_cycles_per_s),
        max_gap_s=float(max_gap_s),
    )


@functools.lru_cache(maxsize=64)
def anchor_numbers(anchor: GeodeticAnchor) -> np.ndarray:
    """``gnss_kernel.anchor_array`` of an anchor (read-only), built once per anchor: its radii of curvature
    cost microseconds, and a session's anchor stays."""
    numbers = anchor_array(anchor)
    numbers.flags.writeable = False
    return numbers


def north_east_up(lat: float, lon: float) -> np.ndarray:
    """Rows: the local north, east and up unit vectors (ECEF) at a latitude and longitude (rad), the state's
    position order."""
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    return np.array([[-sl * co, -sl * so, cl], [-so, co, 0.0], [cl * co, cl * so, sl]])
