"""The phase differences' per-epoch loops compiled (numba): ``fit_kernel`` for ``gnss.tdcp``'s ``fit_rows``
(weighted least squares with the chi-square exclusions, some twenty numpy calls on (n, 4) arrays there);
``terms_kernel`` and ``differences_kernel`` for its ``model_terms`` and the slip tests and rows of
``displacement`` (a Python loop over the satellites and a dozen small numpy calls there); ``shift_kernel``
and ``map_kernel`` for the cloud's move (``move_kernel``, the numpy form ``gnss_tdcp.shift_cloud``);
``displacement_kernel`` the terms, differences and fit together, and ``epoch_kernel`` the whole displacement
step in one call (the numpy form ``gnss_tdcp.reference_step``); ``posterior_terms_kernel`` for the
history's receiver and terms in ``gnss_tdcp.remember_phases``. With one call per step the UPF epoch with
``hatch+tdcp`` is 1.85 ms against Hatch's 1.76 ms (median thread CPU, load 1.1, docs/gnss.md).

The numpy forms stay the reference (run when ``EDGEPOS_NUMBA=0``; tests hold the kernels to them). The
terms, slip tests, differences, the rotation (its 3 x 3 products in index order in both) and the cloud's
move follow numpy's operations one by one and give the same
bits (the receiver at the posterior too where numpy's sin and cos are libm's, as here); in the fit the
normal matrix is inverted by Gauss-Jordan elimination with partial pivoting where numpy inverts by LAPACK's
LU and sums run in index order: the numbers agree to about 1e-12 relative (tested) and the rows left out
are the same, but for a tie: with one degree of freedom left every standardised residual is the same, and
rounding picks the row (the epoch then has too few rows either way: no displacement).
"""

from __future__ import annotations

import math

import numpy as np

from edgepos.core.kernels_base import FAILED, OK, _jit, _symmetrize
from edgepos.core.measurements.gnss_geometry import delays_kernel
from edgepos.core.motion import riss as layout
from edgepos.core.numerics import FloatArray
from edgepos.gnss.tdcp import DIFFERENCED, GAP, LOSS_OF_LOCK, NO_PHASE, NO_PREVIOUS, SLIP

INCONSISTENT = 2
"""``fit_kernel``: fewer than the minimum rows left consistent."""
_UNKNOWNS = 4


@_jit
def _invert(normal: FloatArray, out: FloatArray, max_condition: float) -> bool:
    """``out`` = inverse of the 4 x 4 ``normal`` (Gauss-Jordan, partial pivoting); False when singular or its
    infinity-norm condition number is beyond ``max_condition`` (``gnss.tdcp``'s test)."""
    work = normal.copy()
    for i in range(_UNKNOWNS):
        for j in range(_UNKNOWNS):
            out[i, j] = 1.0 if i == j else 0.0
    for column in range(_UNKNOWNS):
        pivot = column
        for row in range(column + 1, _UNKNOWNS):
            if abs(work[row, column]) > abs(work[pivot, column]):
                pivot = row
        if work[pivot, column] == 0.0 or not math.isfinite(work[pivot, column]):
            return False
        if pivot != column:
            for j in range(_UNKNOWNS):
                work[column, j], work[pivot, j] = work[pivot, j], work[column, j]
                out[column, j], out[pivot, j] = out[pivot, j], out[column, j]
        scale = 1.0 / work[column, column]
        for j in range(_UNKNOWNS):
            work[column, j] *= scale
            out[column, j] *= scale
        for row in range(_UNKNOWNS):
            if row != column:
                factor = work[row, column]
                if factor != 0.0:
                    for j in range(_UNKNOWNS):
                        work[row, j] -= factor * work[column, j]
                        out[row, j] -= factor * out[column, j]
    largest, largest_inverse = 0.0, 0.0
    for i in range(_UNKNOWNS):
        total, total_inverse = 0.0, 0.0
        for j in range(_UNKNOWNS):
            if not math.isfinite(out[i, j]):
                return False
            total += abs(normal[i, j])
            total_inverse += abs(out[i, j])
        largest, largest_inverse = max(largest, total), max(largest_inverse, total_inverse)
    return largest * largest_inverse <= max_condition


@_jit
def fit_kernel(
    y: FloatArray,
    design: FloatArray,
    std: FloatArray,
    bounds: FloatArray,
    min_rows: int,
    max_condition: float,
    keep: np.ndarray,
    solution: FloatArray,
    cov: FloatArray,
    left_out: FloatArray,
) -> int:
    """``gnss.tdcp._fit``'s loop: weighted least squares of the kept rows (``keep``, bool, all true on entry),
    the chi-square test of the weighted residuals against ``bounds[dof]``, and while it fails the row with the
    largest standardised residual left out (``left_out[row]`` = its residual in metres and sigmas). Returns
    OK (``solution``, ``cov`` set), FAILED (singular geometry) or INCONSISTENT (fewer than ``min_rows``
    left; ``keep`` then holds the rows still in)."""
    n = y.shape[0]
    a = np.empty((n, _UNKNOWNS))
    b = np.empty(n)
    normal = np.empty((_UNKNOWNS, _UNKNOWNS))
    rhs = np.empty(_UNKNOWNS)
    weighted = np.empty(n)
    count = n
    while True:
        for i in range(n):
            root = 1.0 / std[i]
            b[i] = y[i] * root
            for j in range(_UNKNOWNS):
                a[i, j] = design[i, j] * root
        for j in range(_UNKNOWNS):
            rhs[j] = 0.0
            for k in range(_UNKNOWNS):
                normal[j, k] = 0.0
        for i in range(n):
            if keep[i]:
                for j in range(_UNKNOWNS):
                    rhs[j] += a[i, j] * b[i]
                    for k in range(_UNKNOWNS):
                        normal[j, k] += a[i, j] * a[i, k]
        if not _invert(normal, cov, max_condition):
            return FAILED
        for j in range(_UNKNOWNS):
            total = 0.0
            for k in range(_UNKNOWNS):
                total += cov[j, k] * rhs[k]
            solution[j] = total
        statistic = 0.0
        for i in range(n):
            if keep[i]:
                fitted = 0.0
                for j in range(_UNKNOWNS):
                    fitted += a[i, j] * solution[j]
                weighted[i] = b[i] - fitted
                statistic += weighted[i] * weighted[i]
        if statistic <= bounds[count - _UNKNOWNS]:
            return OK
        worst, largest = -1, -1.0
        for i in range(n):
            if keep[i]:
                leverage = 0.0
                for j in range(_UNKNOWNS):
                    for k in range(_UNKNOWNS):
                        leverage += a[i, j] * cov[j, k] * a[i, k]
                standardised = abs(weighted[i]) / math.sqrt(max(1.0 - leverage, 1e-9))
                if standardised > largest:
                    worst, largest = i, standardised
        keep[worst] = False
        left_out[worst, 0] = weighted[worst] * std[worst]
        left_out[worst, 1] = largest
        count -= 1
        if count < min_rows:
            return INCONSISTENT


@_jit
def terms_kernel(
    receiver: FloatArray,
    sat_position: FloatArray,
    sat_clock_s: FloatArray,
    troposphere_m: FloatArray,
    ionosphere_m: FloatArray,
    omega_earth: float,
    speed_of_light: float,
    out: FloatArray,
) -> None:
    """``gnss.tdcp.model_terms`` row by row (the Sagnac range, then the clock and the delays, in its order of
    operations: the same bits)."""
    rx, ry, rz = receiver[0], receiver[1], receiver[2]
    for i in range(sat_position.shape[0]):
        sx, sy, sz = sat_position[i, 0], sat_position[i, 1], sat_position[i, 2]
        dx, dy, dz = sx - rx, sy - ry, sz - rz
        geometric = math.sqrt(dx * dx + dy * dy + dz * dz)
        sagnac = omega_earth * (sx * ry - sy * rx)
        value = geometric + sagnac / speed_of_light - speed_of_light * sat_clock_s[i]
        out[i] = value + troposphere_m[i] - ionosphere_m[i]


@_jit
def differences_kernel(
    cycles: FloatArray,
    before: FloatArray,
    dt: float,
    max_gap_s: float,
    slip_cycles_per_s: float,
    doppler_hz: FloatArray,
    lli: np.ndarray,
    wavelength_m: FloatArray,
    sat_position: FloatArray,
    receiver: FloatArray,
    terms_now: FloatArray,
    std_all: FloatArray,
    status: np.ndarray,
    off: FloatArray,
    index: np.ndarray,
    y: FloatArray,
    design: FloatArray,
    std: FloatArray,
) -> int:
    """``gnss.tdcp.displacement`` before its fit: per row its ``gnss.tdcp`` code (``status``; ``off`` the cycles off the
    Doppler for SLIP), and the differenced rows' index, difference ``y``, design row and std, packed at the
    front; returns how many. ``before``: per row the previous epoch's [cycles, model term] (NaN: none)."""
    count = 0
    for row in range(cycles.shape[0]):
        value = cycles[row]
        if not math.isfinite(value):
            status[row] = NO_PHASE
            continue
        if not math.isfinite(before[row, 0]):
            status[row] = NO_PREVIOUS
            continue
        if lli[row] & 1:
            status[row] = LOSS_OF_LOCK
            continue
        if not 0.0 < dt <= max_gap_s:
            status[row] = GAP
            continue
        if math.isfinite(doppler_hz[row]):
            change = value - before[row, 0] + doppler_hz[row] * dt
            if abs(change) > slip_cycles_per_s * dt:
                status[row] = SLIP
                off[row] = change
                continue
        status[row] = DIFFERENCED
        index[count] = row
        y[count] = wavelength_m[row] * (value - before[row, 0]) - terms_now[row] + before[row, 1]
        tx = sat_position[row, 0] - receiver[0]
        ty = sat_position[row, 1] - receiver[1]
        tz = sat_position[row, 2] - receiver[2]
        norm = -math.sqrt(tx * tx + ty * ty + tz * tz)
        design[count, 0], design[count, 1], design[count, 2] = tx / norm, ty / norm, tz / norm
        design[count, 3] = 1.0
        std[count] = std_all[row]
        count += 1
    return count


TOO_FEW = 3
"""``displacement_kernel``: fewer differenced rows than the fit needs (no fit run)."""
LEFT_OUT, SINGULAR, INCONSISTENT_ROW, FEW = range(NO_PHASE + 1, NO_PHASE + 5)
"""``epoch_kernel``'s row codes after ``gnss.tdcp``'s (DIFFERENCED .. NO_PHASE): a differenced row left out
by the fit, in a singular or an inconsistent fit, or one of too few to fit."""


@_jit
def displacement_kernel(
    receiver: FloatArray,
    sat_position: FloatArray,
    sat_clock_s: FloatArray,
    troposphere_m: FloatArray,
    ionosphere_m: FloatArray,
    constants: FloatArray,
    cycles: FloatArray,
    history: FloatArray,
    history_row: np.ndarray,
    doppler_hz: FloatArray,
    lli: np.ndarray,
    wavelength_m: FloatArray,
    std_all: FloatArray,
    bounds: FloatArray,
    min_rows: int,
    status: np.ndarray,
    off: FloatArray,
    index: np.ndarray,
    keep: np.ndarray,
    left_out: FloatArray,
    solution: FloatArray,
    cov: FloatArray,
) -> tuple[int, int]:
    """The epoch's whole ``gnss.tdcp.displacement`` in one call: the model terms at the previous ``receiver``
    (``terms_kernel``), each row's previous [cycles, term] (``history[history_row[row]]``, none where -1),
    the slip tests and differences (``differences_kernel``) and the fit of the differenced rows
    (``fit_kernel``). ``constants``: omega_earth, speed of light, dt, max gap (s), slip cycles per second,
    max condition. Returns (how many rows were differenced, packed at the front of ``index``; the fit's
    OK, FAILED or INCONSISTENT, or TOO_FEW when fewer than ``min_rows`` were)."""
    n = cycles.shape[0]
    terms = np.empty(n)
    terms_kernel(
        receiver, sat_position, sat_clock_s, troposphere_m, ionosphere_m, constants[0], constants[1], terms
    )
    before = np.empty((n, 2))
    for row in range(n):
        k = history_row[row]
        if k < 0:
            before[row, 0], before[row, 1] = math.nan, math.nan
        else:
            before[row, 0], before[row, 1] = history[k, 0], history[k, 1]
    y, design, std = np.empty(n), np.empty((n, _UNKNOWNS)), np.empty(n)
    count = differences_kernel(
        cycles,
        before,
        constants[2],
        constants[3],
        constants[4],
        doppler_hz,
        lli,
        wavelength_m,
        sat_position,
        receiver,
        terms,
        std_all,
        status,
        off,
        index,
        y,
        design,
        std,
    )
    if count < min_rows:
        return count, TOO_FEW
    for i in range(count):
        keep[i] = True
    outcome = fit_kernel(
        y[:count],
        design[:count],
        std[:count],
        bounds,
        min_rows,
        constants[5],
        keep[:count],
        solution,
        cov,
        left_out[:count],
    )
    return count, outcome


@_jit
def epoch_kernel(
    receiver: FloatArray,
    sat_position: FloatArray,
    frequency_hz: FloatArray,
    sat_clock_s: FloatArray,
    klobuchar: FloatArray,
    constants: FloatArray,
    cycles: FloatArray,
    history: FloatArray,
    history_row: np.ndarray,
    doppler_hz: FloatArray,
    lli: np.ndarray,
    bounds: FloatArray,
    anchor: FloatArray,
    mean: FloatArray,
    particles: FloatArray,
    cloud_cov: FloatArray,
    moments_mean: FloatArray,
    moments_cov: FloatArray,
    status: np.ndarray,
    values: FloatArray,
    solution: FloatArray,
    fit_cov: FloatArray,
    noise: FloatArray,
    process_noise: FloatArray,
    out_particles: FloatArray,
    out_cov: FloatArray,
    out_mean: FloatArray,
    out_moments_cov: FloatArray,
) -> tuple[int, int]:
    """An epoch's whole displacement step (``gnss_tdcp.predict_with_displacement``) in one call: the delays
    and elevations at the previous ``receiver`` (``gnss_geometry.delays_kernel``), each difference's std ``phase_std`` / max(sin(elevation), ``min_sin``), the
    differences and fit (``displacement_kernel``); when the fit gives a displacement, its rotation to the
    state's north/east/up at ``mean``'s latitude and longitude (``gnss_tdcp.rotated``'s order of
    operations), the displacement model's position noise (``noise``; in ``process_noise``, the
    constant-velocity model's Q, as ``gnss_tdcp.DisplacementModel.remember_noise`` puts it) and the cloud's move
    (``move_kernel``: the particles, their covariance and the remembered moments, empty when none, into the
    ``out_`` arrays).
    ``constants``: omega_earth, speed of light, dt, max gap, slip cycles per second, max condition,
    phase_std, min_sin, the GPS seconds of the epoch, min rows, Klobuchar on (1) or off (0), the
    troposphere on or off, the position variances' floor. Per row ``status`` is its code (``gnss.tdcp``'s,
    or what the fit made of it: LEFT_OUT, SINGULAR, INCONSISTENT_ROW, FEW) and ``values`` its numbers (SLIP:
    the cycles off the Doppler; LEFT_OUT: the residual in metres and sigmas). Returns as
    ``displacement_kernel``."""
    n = cycles.shape[0]
    delays = np.empty((4, n))
    delays_kernel(
        receiver,
        sat_position,
        frequency_hz,
        klobuchar,
        constants[10] != 0.0,
        constants[11] != 0.0,
        constants[8],
        delays,
    )
    wavelength, std_all = np.empty(n), np.empty(n)
    for i in range(n):
        wavelength[i] = constants[1] / frequency_hz[i]
        std_all[i] = constants[6] / max(math.sin(delays[2, i]), constants[7])
    off, index, keep, left_out = (
        np.zeros(n),
        np.empty(n, dtype=np.int64),
        np.zeros(n, np.bool_),
        np.zeros((n, 2)),
    )
    count, outcome = displacement_kernel(
        receiver,
        sat_position,
        sat_clock_s,
        delays[1],
        delays[0],
        constants,
        cycles,
        history,
        history_row,
        doppler_hz,
        lli,
        wavelength,
        std_all,
        bounds,
        int(constants[9]),
        status,
        off,
        index,
        keep,
        left_out,
        solution,
        fit_cov,
    )
    for row in range(n):
        values[row, 0] = off[row]
        values[row, 1] = 0.0
    for i in range(count):  # the differenced rows: what the fit made of each
        row = index[i]
        if outcome == TOO_FEW:
            status[row] = FEW
        elif not keep[i]:
            status[row] = LEFT_OUT
            values[row, 0], values[row, 1] = left_out[i, 0], left_out[i, 1]
        elif outcome == FAILED:
            status[row] = SINGULAR
        elif outcome == INCONSISTENT:
            status[row] = INCONSISTENT_ROW
    if outcome != OK:
        return count, outcome
    lat = anchor[0] + mean[layout.NORTH] / anchor[3]
    lon = anchor[1] + mean[layout.EAST] / anchor[4]
    sl, cl, so, co = math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)
    rotation = np.array([[-sl * co, -sl * so, cl], [-so, co, 0.0], [cl * co, cl * so, sl]])
    step = np.empty(3)
    rotated = np.empty((3, 3))
    for i in range(3):
        step[i] = (rotation[i, 0] * solution[0] + rotation[i, 1] * solution[1]) + rotation[i, 2] * solution[2]
        for j in range(3):
            rotated[i, j] = (rotation[i, 0] * fit_cov[0, j] + rotation[i, 1] * fit_cov[1, j]) + rotation[
                i, 2
            ] * fit_cov[2, j]
    for i in range(3):
        for j in range(3):
            noise[i, j] = (rotated[i, 0] * rotation[j, 0] + rotated[i, 1] * rotation[j, 1]) + rotated[
                i, 2
            ] * rotation[j, 2]
    _symmetrize(noise, 3)
    positions = (layout.NORTH, layout.EAST, layout.UP)
    velocities = (layout.VN, layout.VE, layout.VU)
    for i in range(3):
        process_noise[positions[i], velocities[i]] = 0.0
        process_noise[velocities[i], positions[i]] = 0.0
        for j in range(3):
            floor = constants[12] if i == j else 0.0
            process_noise[positions[i], positions[j]] = noise[i, j] + floor
    move_kernel(
        particles,
        cloud_cov,
        moments_mean,
        moments_cov,
        step,
        constants[2],
        out_particles,
        out_cov,
        out_mean,
        out_moments_cov,
    )
    return count, outcome


@_jit
def shift_kernel(particles: FloatArray, step: FloatArray, dt: float, out: FloatArray) -> None:
    """``gnss_tdcp.shift_cloud``'s particles: ``out`` = ``particles`` with each position (north, east, up)
    moved by ``step`` less its velocity times ``dt``, in the numpy form's order of operations (the same
    bits)."""
    for i in range(particles.shape[0]):
        for j in range(particles.shape[1]):
            out[i, j] = particles[i, j]
        out[i, layout.NORTH] = (particles[i, layout.NORTH] + step[0]) - particles[i, layout.VN] * dt
        out[i, layout.EAST] = (particles[i, layout.EAST] + step[1]) - particles[i, layout.VE] * dt
        out[i, layout.UP] = (particles[i, layout.UP] + step[2]) - particles[i, layout.VU] * dt


@_jit
def map_kernel(cov: FloatArray, dt: float, out: FloatArray) -> None:
    """``gnss_tdcp._mapped``: ``out`` = T C T^T, T the identity with -dt from each velocity to its position,
    made symmetric as there; row and column operations where numpy multiplies the full matrices (the same
    numbers but for the last bit of the position rows and columns)."""
    n = cov.shape[0]
    for i in range(n):
        for j in range(n):
            out[i, j] = cov[i, j]
    for position, velocity in ((layout.NORTH, layout.VN), (layout.EAST, layout.VE), (layout.UP, layout.VU)):
        for j in range(n):
            out[position, j] = cov[position, j] - dt * cov[velocity, j]
    for position, velocity in ((layout.NORTH, layout.VN), (layout.EAST, layout.VE), (layout.UP, layout.VU)):
        for i in range(n):
            out[i, position] = out[i, position] - dt * out[i, velocity]
    _symmetrize(out, n)


@_jit
def move_kernel(
    particles: FloatArray,
    cov: FloatArray,
    moments_mean: FloatArray,
    moments_cov: FloatArray,
    step: FloatArray,
    dt: float,
    out_particles: FloatArray,
    out_cov: FloatArray,
    out_mean: FloatArray,
    out_moments_cov: FloatArray,
) -> None:
    """``gnss_tdcp.shift_cloud`` in one call: the particles (``shift_kernel``), their covariance
    (``map_kernel``) and, when ``moments_mean`` is not empty, the remembered moments: the mean's positions
    plus (``step`` less their velocities times ``dt``), in the numpy form's order, and the covariance by
    ``map_kernel`` (the same bits as the numpy form)."""
    shift_kernel(particles, step, dt, out_particles)
    map_kernel(cov, dt, out_cov)
    if moments_mean.shape[0] == 0:
        return
    for j in range(moments_mean.shape[0]):
        out_mean[j] = moments_mean[j]
    out_mean[layout.NORTH] = moments_mean[layout.NORTH] + (step[0] - moments_mean[layout.VN] * dt)
    out_mean[layout.EAST] = moments_mean[layout.EAST] + (step[1] - moments_mean[layout.VE] * dt)
    out_mean[layout.UP] = moments_mean[layout.UP] + (step[2] - moments_mean[layout.VU] * dt)
    map_kernel(moments_cov, dt, out_moments_cov)


@_jit
def posterior_terms_kernel(
    anchor: FloatArray,
    posterior: FloatArray,
    semi_major_m: float,
    eccentricity2: float,
    sat_position: FloatArray,
    sat_clock_s: FloatArray,
    troposphere_m: FloatArray,
    ionosphere_m: FloatArray,
    omega_earth: float,
    speed_of_light: float,
    cycles: FloatArray,
    receiver: FloatArray,
    table: FloatArray,
    index: np.ndarray,
) -> int:
    """``gnss_tdcp.remember_phases``'s receiver (``anchor.ecef`` of the posterior state: ``anchor`` as
    ``gnss_kernel.anchor_array``, then ``geodesy.geodetic_to_ecef``'s formula in its order of operations) and
    the model terms there (``terms_kernel``), packed with the rows' ``cycles`` into ``table`` [cycles, term]
    for the rows with a phase (``index``: their rows); returns how many."""
    lat = anchor[0] + posterior[layout.NORTH] / anchor[3]
    lon = anchor[1] + posterior[layout.EAST] / anchor[4]
    height = anchor[2] + posterior[layout.UP]
    sin_lat = math.sin(lat)
    prime_vertical = semi_major_m / math.sqrt(1.0 - eccentricity2 * sin_lat * sin_lat)
    horizontal = (prime_vertical + height) * math.cos(lat)
    receiver[0] = horizontal * math.cos(lon)
    receiver[1] = horizontal * math.sin(lon)
    receiver[2] = (prime_vertical * (1.0 - eccentricity2) + height) * sin_lat
    terms = np.empty(cycles.shape[0])
    terms_kernel(
        receiver, sat_position, sat_clock_s, troposphere_m, ionosphere_m, omega_earth, speed_of_light, terms
    )
    count = 0
    for row in range(cycles.shape[0]):
        if math.isfinite(cycles[row]):
            table[count, 0], table[count, 1] = cycles[row], terms[row]
            index[count] = row
            count += 1
    return count
