"""gnss_tight's pseudorange and range-rate predictions in one compiled loop (numba), for the filters' batches
of states: the same equations as ``pseudorange.PseudorangeModel.predict_at`` and
``range_rate.RangeRateModel.predict_at`` (their numpy forms stay the reference the kernel is tested against,
and run when ``EDGEPOS_NUMBA=0``).

The numpy forms cost some forty array operations per call, each a few microseconds of overhead on the UPF's
200-400 states x 20-40 satellites; the loop computes each state's position and velocity once and every
satellite's range and rate from them, with no temporaries. The range is taken as |s - r| directly (the
numpy form's |s|^2 - 2 r.s + |r|^2 loses 1e-8 m to cancellation; the kernel does not).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from edgepos.core.compiled import compiled_enabled
from edgepos.core.kernels_base import _jit
from edgepos.core.measurements.pseudorange import PseudorangeModel
from edgepos.core.measurements.range_rate import RangeRateModel
from edgepos.core.motion.riss import CLOCK, DIM, DRIFT, EAST, NORTH, UP, VE, VN, VU, GeodeticAnchor
from edgepos.core.numerics import FloatArray
from edgepos.gnss.geodesy import WGS84_A, WGS84_E2, geodetic_to_ecef
from edgepos.gnss.orbits import OMEGA_EARTH, SPEED_OF_LIGHT

_SAGNAC = OMEGA_EARTH / SPEED_OF_LIGHT


@_jit
def predict_ranges(
    states: FloatArray,
    anchor: FloatArray,
    pr_sat: FloatArray,
    pr_clock: np.ndarray,
    pr_known: FloatArray,
    rate_sat: FloatArray,
    rate_velocity: FloatArray,
    rate_known: FloatArray,
    out: FloatArray,
) -> None:
    """Rows of ``out`` (n, m1 + m2): the m1 pseudoranges then the m2 range rates of each state (n, DIM).

    ``anchor``: lat0, lon0, height0, north scale, east scale (``GeodeticAnchor``); pseudoranges: satellite
    positions (m1, 3), clock-bias state index (m1,) and known terms (m1,); range rates: satellite positions
    and velocities (m2, 3) and known terms (m2,)."""
    m1 = pr_sat.shape[0]
    m2 = rate_sat.shape[0]
    for i in range(states.shape[0]):
        lat = anchor[0] + states[i, NORTH] / anchor[3]
        lon = anchor[1] + states[i, EAST] / anchor[4]
        height = anchor[2] + states[i, UP]
        sin_lat, cos_lat = math.sin(lat), math.cos(lat)
        sin_lon, cos_lon = math.sin(lon), math.cos(lon)
        normal = WGS84_A / math.sqrt(1.0 - WGS84_E2 * sin_lat * sin_lat)
        horizontal = (normal + height) * cos_lat
        rx, ry, rz = (
            horizontal * cos_lon,
            horizontal * sin_lon,
            (normal * (1.0 - WGS84_E2) + height) * sin_lat,
        )
        for j in range(m1):
            dx, dy, dz = pr_sat[j, 0] - rx, pr_sat[j, 1] - ry, pr_sat[j, 2] - rz
            sagnac = _SAGNAC * (pr_sat[j, 0] * ry - pr_sat[j, 1] * rx)
            out[i, j] = math.sqrt(dx * dx + dy * dy + dz * dz) + sagnac + states[i, pr_clock[j]] + pr_known[j]
        if m2 == 0:
            continue
        ve, vn, vu = states[i, VE], states[i, VN], states[i, VU]
        vx = -sin_lon * ve - sin_lat * cos_lon * vn + cos_lat * cos_lon * vu
        vy = cos_lon * ve - sin_lat * sin_lon * vn + cos_lat * sin_lon * vu
        vz = cos_lat * vn + sin_lat * vu
        drift = states[i, DRIFT]
        for j in range(m2):
            sx, sy, sz = rate_sat[j, 0], rate_sat[j, 1], rate_sat[j, 2]
            wx, wy, wz = rate_velocity[j, 0], rate_velocity[j, 1], rate_velocity[j, 2]
            dx, dy, dz = sx - rx, sy - ry, sz - rz
            distance = math.sqrt(dx * dx + dy * dy + dz * dz)
            along = dx * (wx - vx) + dy * (wy - vy) + dz * (wz - vz)
            sagnac = _SAGNAC * (wx * ry + sx * vy - wy * rx - sy * vx)
            out[i, m1 + j] = along / distance + sagnac + drift + rate_known[j]


def anchor_array(anchor: GeodeticAnchor) -> FloatArray:
    """The anchor as the kernel takes it."""
    return np.array([anchor.lat, anchor.lon, anchor.height, anchor.scale_north, anchor.scale_east])


def predict(
    states: np.ndarray,
    anchor: FloatArray,
    pr_sat: FloatArray,
    pr_clock: np.ndarray,
    pr_known: FloatArray,
    rate_sat: FloatArray,
    rate_velocity: FloatArray,
    rate_known: FloatArray,
) -> FloatArray:
    """:func:`predict_ranges` over any leading axes of ``states`` (..., DIM) -> (..., m1 + m2)."""
    flat = np.ascontiguousarray(states.reshape(-1, states.shape[-1]), dtype=float)
    out = np.empty((flat.shape[0], len(pr_known) + len(rate_known)))
    predict_ranges(flat, anchor, pr_sat, pr_clock, pr_known, rate_sat, rate_velocity, rate_known, out)
    result: FloatArray = out.reshape(states.shape[:-1] + (out.shape[1],))
    return result


def epoch_predict(
    pseudoranges: PseudorangeModel, rates: RangeRateModel | None
) -> Callable[[np.ndarray], np.ndarray]:
    """h of an epoch's update, states (..., DIM) -> the pseudoranges then the range rates (..., m1 + m2):
    the compiled kernel, or the models' numpy forms when ``EDGEPOS_NUMBA=0`` (or numba is missing)."""
    if compiled_enabled():
        empty = np.zeros((0, 3))
        arguments = (
            anchor_array(pseudoranges.anchor),
            np.ascontiguousarray(pseudoranges.sat_position, dtype=float),
            pseudoranges.clock_index.astype(np.int64),
            np.ascontiguousarray(pseudoranges.known_m, dtype=float),
            empty if rates is None else np.ascontiguousarray(rates.sat_position, dtype=float),
            empty if rates is None else np.ascontiguousarray(rates.sat_velocity, dtype=float),
            np.zeros(0) if rates is None else np.ascontiguousarray(rates.known_mps, dtype=float),
        )
        return lambda states: predict(states, *arguments)
    if rates is None:
        return pseudoranges.predict
    anchor = pseudoranges.anchor

    def reference(states: np.ndarray) -> np.ndarray:
        lat, lon, height = anchor.geodetic(states)
        receiver = geodetic_to_ecef(lat, lon, height)
        return np.concatenate(
            [pseudoranges.predict_at(states, receiver), rates.predict_at(states, lat, lon, receiver)],
            axis=-1,
        )

    return reference


def pseudoranges_at(
    anchor: GeodeticAnchor,
    states: np.ndarray,
    sat_position: np.ndarray,
    systems: Sequence[str],
    known_m: np.ndarray,
) -> FloatArray | None:
    """The pseudoranges (k, m) of states (k, DIM) by the kernel (``PseudorangeModel.predict``'s equation:
    satellites (m, 3), their constellations and known terms); None when the kernels are off. Each state's
    and satellite's value is computed alone, so a subset of the rows or states gives the same numbers (the
    pipeline's shared prediction and a test's own agree exactly)."""
    if not compiled_enabled():
        return None
    empty = np.zeros((0, 3))
    return predict(
        np.asarray(states, dtype=float),
        anchor_array(anchor),
        np.ascontiguousarray(sat_position, dtype=float).reshape(-1, 3),
        np.array([CLOCK[s] for s in systems], dtype=np.int64),
        np.ascontiguousarray(known_m, dtype=float),
        empty,
        empty,
        np.zeros(0),
    )


def range_rates_at(
    anchor: GeodeticAnchor,
    states: np.ndarray,
    sat_position: np.ndarray,
    sat_velocity: np.ndarray,
    sat_clock_drift: np.ndarray,
) -> FloatArray | None:
    """The range rates (k, m) of states (k, DIM) by the kernel (``RangeRateModel.build(...).predict``'s
    equation, from the satellites' positions, velocities and clock drifts (s/s)); None when the kernels are
    off. Each value is computed alone, as in :func:`pseudoranges_at`."""
    if not compiled_enabled():
        return None
    return predict(
        np.asarray(states, dtype=float),
        anchor_array(anchor),
        np.zeros((0, 3)),
        np.zeros(0, dtype=np.int64),
        np.zeros(0),
        np.ascontiguousarray(sat_position, dtype=float).reshape(-1, 3),
        np.ascontiguousarray(sat_velocity, dtype=float).reshape(-1, 3),
        -SPEED_OF_LIGHT * np.ascontiguousarray(sat_clock_drift, dtype=float),
    )


def warm_up() -> float:
    """Compile (or load from numba's on-disk cache) the kernel's one signature; returns the seconds."""
    started = time.perf_counter()
    empty = np.zeros((0, 3))
    predict(
        np.zeros((1, DIM)),
        np.array([0.7, 0.04, 200.0, 6.4e6, 4.9e6]),
        np.array([[2.0e7, 1.0e7, 1.5e7]]),
        np.array([9], dtype=np.int64),
        np.zeros(1),
        empty,
        empty,
        np.zeros(0),
    )
    return time.perf_counter() - started
