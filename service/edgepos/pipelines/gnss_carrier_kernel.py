"""The Hatch filter's per-satellite loop compiled (numba): ``hatch_kernel`` is ``gnss.carrier.hatch_update``
on the session's track table (``gnss.carrier.CarrierTable``) instead of a dict of track objects: the same
slip tests in the same order, the same arithmetic in the same order (the smoothed ranges and counts to the
bit; tested on the recording with slips put in, tests/pipelines/test_pipeline_gnss_carrier_kernel.py), and
the new table with the tracks updated this epoch first, then the older ones still within the gap. The
restart reasons are codes (the pipeline reads only the smoothed ranges and counts).
"""

from __future__ import annotations

import math

import numpy as np

from edgepos.core.kernels_base import _jit
from edgepos.core.numerics import FloatArray

CONTINUED, LOSS_OF_LOCK, GAP, SLIP, CODE_JUMP = range(5)
"""``hatch_kernel``'s restart codes, in ``gnss.carrier._slip``'s order (CONTINUED: no restart)."""


@_jit
def hatch_kernel(
    t: float,
    codes: FloatArray,
    cycles: FloatArray,
    wavelength_m: FloatArray,
    doppler_hz: FloatArray,
    lli: np.ndarray,
    track_row: np.ndarray,
    table: FloatArray,
    settings: FloatArray,
    smoothed: FloatArray,
    count: FloatArray,
    reset: np.ndarray,
    new_table: FloatArray,
    origin: np.ndarray,
) -> int:
    """``hatch_update`` row by row: ``track_row`` each row's track in ``table`` (-1: none), ``settings`` the
    window, slip cycles per second, code jump (m) and max gap (s). Fills ``smoothed`` and ``count`` (the
    raw code and 0 for rows without a phase), ``reset`` (a code per row), and ``new_table`` with ``origin``
    (the epoch's row r as r, an older track k as -1 - k); returns the new table's rows."""
    window, slip_cycles_per_s, code_jump_m, max_gap_s = settings[0], settings[1], settings[2], settings[3]
    n = codes.shape[0]
    updated = np.zeros(table.shape[0], dtype=np.bool_)
    rows = 0
    for row in range(n):
        code = codes[row]
        smoothed[row] = code
        count[row] = 0.0
        reset[row] = CONTINUED
        value_cycles = cycles[row]
        if not math.isfinite(value_cycles):
            continue
        lam = wavelength_m[row]
        has_doppler = math.isfinite(doppler_hz[row])
        k = track_row[row]
        why = CONTINUED
        if k >= 0:
            updated[k] = True
            dt = t - table[k, 0]
            change = value_cycles - table[k, 3]
            if lli[row] & 1:
                why = LOSS_OF_LOCK
            elif not 0.0 < dt <= max_gap_s:
                why = GAP
            else:
                if has_doppler or table[k, 5] != 0.0:
                    total, rates = 0.0, 0.0
                    if table[k, 5] != 0.0:
                        total, rates = total + table[k, 4], rates + 1.0
                    if has_doppler:
                        total, rates = total + doppler_hz[row], rates + 1.0
                    predicted = -total / rates * dt
                    if abs(change - predicted) > slip_cycles_per_s * dt:
                        why = SLIP
                if why == CONTINUED:
                    jump = code - (table[k, 2] + lam * change)
                    if abs(jump) > code_jump_m:
                        why = CODE_JUMP
        if why != CONTINUED or k < 0:
            value, used = code, 1.0
            reset[row] = why
        else:
            dt = t - table[k, 0]
            used = min(table[k, 1] + 1.0, max(1.0, window / dt))
            propagated = table[k, 2] + lam * (value_cycles - table[k, 3])
            value = code / used + (used - 1.0) / used * propagated
        new_table[rows, 0] = t
        new_table[rows, 1] = used
        new_table[rows, 2] = value
        new_table[rows, 3] = value_cycles
        new_table[rows, 4] = doppler_hz[row] if has_doppler else 0.0
        new_table[rows, 5] = 1.0 if has_doppler else 0.0
        origin[rows] = row
        rows += 1
        smoothed[row] = value
        count[row] = used
    for k in range(table.shape[0]):
        if not updated[k] and not t - table[k, 0] > max_gap_s:
            for j in range(table.shape[1]):
                new_table[rows, j] = table[k, j]
            origin[rows] = -1 - k
            rows += 1
    return rows
