"""Carrier-smoothed code (Hatch filter) per satellite, with cycle-slip detection. Pure numpy.

A receiver's carrier phase (cycles, times the wavelength: metres) follows the range change to millimetres
but carries an unknown constant (the integer ambiguity); its code pseudorange is absolute but metres noisy.
The Hatch filter averages the code-minus-carrier difference (constant while lock holds, up to the
ionosphere) and adds the carrier back:

    S_k = P_k / n + (n - 1) / n * (S_{k-1} + lambda (L_k - L_{k-1})),   n = min(epochs since reset, N)

so for n <= N, S_k = mean_i(P_i - lambda L_i) + lambda L_k: the average of code-minus-carrier plus carrier.
N = window / (time since the previous epoch) bounds the memory. On one frequency the ionosphere delays the
code and advances the phase by the same amount, so the average drifts from the code by twice the ionosphere's
change over the window (the code-carrier divergence): at the few mm/s the ionosphere changes in mid-latitude
daytime, a 100 s window keeps it at decimetres, below the code multipath it averages away (the SBAS standard,
RTCA DO-229, smooths over 100 s for the same reason).

A cycle slip (the tracking loop losing count) puts a jump into the carrier; the average then carries it into
every later smoothed range. A satellite's smoothing starts again from its raw code (only that satellite's)
when any of these says the phase may have slipped:

* the loss-of-lock indicator: RINEX bit 0 (``lli & 1``), set by the receiver when lock was lost since the
  previous observation (bit 1, a half-cycle ambiguity, moves the phase by half a cycle, 0.1 m: ignored);
* the Doppler-predicted phase: the phase change against the Doppler integrated over the interval
  (trapezoid, ``-(D_prev + D) / 2 * dt`` cycles, RINEX signs: the phase decreases while the Doppler is
  positive), beyond ``slip_cycles_per_s`` times the interval;
* the code-carrier jump: the new code minus the carrier-propagated smoothed range beyond ``code_jump_m``
  (catches large slips when no Doppler is sent; its threshold sits above urban code multipath);
* a gap longer than ``max_gap_s`` since the satellite's previous phase (the Doppler test cannot bridge it).

Two-frequency (geometry-free) slip detection needs the second frequency's phase, which a ``pseudorange``
measurement does not carry (one signal per measurement).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

DEFAULT_WINDOW_S = 100.0
DEFAULT_SLIP_CYCLES_PER_S = 5.0
"""Doppler test threshold: on the first half of tests/data/gnss-rover (1 s epochs, no LLI set) the phase
change minus the integrated Doppler has a median of 0.33 cycles, a 99th percentile of 4.9 cycles; a Doppler
std of 0.25 m/s (the pipeline's doppler_std_mps) is 1.3 L1 cycles per second, and 5 is about four of those."""
DEFAULT_CODE_JUMP_M = 15.0
"""Code-carrier test threshold: on the first half of tests/data/gnss-rover (the other tests on) the code minus
the carrier-propagated smoothed range has a 99.9th percentile of 6.1 m and a maximum of 7.3 m; 15 m is twice
that (a false restart costs one satellite its average; a missed slip of 75 L1 cycles or more would bias it)."""
DEFAULT_MAX_GAP_S = 5.0

_COLUMNS = 6
"""Serialised track: t, count, smoothed_m, phase_cycles, doppler_hz (0 when none), has_doppler (0/1)."""


@dataclass(frozen=True)
class HatchConfig:
    """Settings of the Hatch filter and its slip tests (see the module docstring)."""

    window_s: float = DEFAULT_WINDOW_S
    slip_cycles_per_s: float = DEFAULT_SLIP_CYCLES_PER_S
    code_jump_m: float = DEFAULT_CODE_JUMP_M
    max_gap_s: float = DEFAULT_MAX_GAP_S


@dataclass(frozen=True)
class CarrierTrack:
    """One satellite's smoothing between epochs: the time and phase of its last carrier epoch, the smoothed
    range there, how many epochs it averages (capped by the window) and the Doppler then (None: not sent)."""

    t: float
    count: float
    smoothed_m: float
    phase_cycles: float
    doppler_hz: float | None


def new_track(
    t: float, count: float, smoothed_m: float, phase_cycles: float, doppler_hz: float | None
) -> CarrierTrack:
    """``CarrierTrack(...)`` without its frozen ``__init__`` (one ``object.__setattr__`` per field: 1.7 against
    0.7 us, some thirty tracks an epoch between the update and the state's decoding). Valid because the class
    has no ``__post_init__`` or slots (tests/gnss/test_gnss_carrier.py checks both and holds it to the
    constructor)."""
    track = object.__new__(CarrierTrack)
    fields = track.__dict__
    fields["t"] = t
    fields["count"] = count
    fields["smoothed_m"] = smoothed_m
    fields["phase_cycles"] = phase_cycles
    fields["doppler_hz"] = doppler_hz
    return track


@dataclass(frozen=True)
class HatchResult:
    """Per row of the update: the smoothed pseudorange (m; the raw code where the row had no carrier), the
    epochs it averages (0: no carrier, 1: a restart) and why the satellite's smoothing restarted (None when
    it continued or had no carrier)."""

    pseudorange_m: np.ndarray
    count: np.ndarray
    reset: list[str | None]


def hatch_update(
    tracks: dict[str, CarrierTrack],
    t: float,
    sats: Sequence[str],
    pseudorange_m: np.ndarray,
    carrier_cycles: np.ndarray,
    wavelength_m: np.ndarray,
    doppler_hz: np.ndarray,
    lli: np.ndarray,
    config: HatchConfig,
) -> HatchResult:
    """Advance every satellite's smoothing to epoch ``t``, in place in ``tracks`` (keyed by satellite id).

    Rows with a NaN ``carrier_cycles`` pass their code through and leave their track as it was (a later
    epoch continues it if within ``max_gap_s``); NaN ``doppler_hz`` means no Doppler; ``lli`` is the RINEX
    loss-of-lock indicator (0 when not sent). Tracks older than ``max_gap_s`` are dropped, so the state
    holds at most the satellites of the last few seconds."""
    n = len(sats)
    reset: list[str | None] = [None] * n
    # the rows as Python numbers, read once (the same values as float() / int() of each element), and the
    # results as lists made arrays once (a numpy element written per row costs more)
    all_cycles, codes = np.asarray(carrier_cycles, float).tolist(), np.asarray(pseudorange_m, float).tolist()
    smoothed, count = list(codes), [0.0] * n
    wavelengths, dopplers = np.asarray(wavelength_m, float).tolist(), np.asarray(doppler_hz, float).tolist()
    flags = [int(v) for v in np.asarray(lli).tolist()]
    for row in range(n):
        cycles = all_cycles[row]
        if not math.isfinite(cycles):
            continue
        code = codes[row]
        lam = wavelengths[row]
        doppler = dopplers[row] if math.isfinite(dopplers[row]) else None
        track = tracks.get(sats[row])
        why = _slip(track, t, code, cycles, lam, doppler, flags[row], config)
        if why is not None or track is None:
            value, used = code, 1.0
            reset[row] = why
        else:
            dt = t - track.t
            used = min(track.count + 1.0, max(1.0, config.window_s / dt))
            propagated = track.smoothed_m + lam * (cycles - track.phase_cycles)
            value = code / used + (used - 1.0) / used * propagated
        tracks[sats[row]] = new_track(t, used, value, cycles, doppler)
        smoothed[row] = value
        count[row] = used
    for sat in [s for s, track in tracks.items() if t - track.t > config.max_gap_s]:
        del tracks[sat]
    return HatchResult(np.array(smoothed, dtype=float), np.array(count, dtype=float), reset)


def _slip(
    track: CarrierTrack | None,
    t: float,
    code: float,
    cycles: float,
    lam: float,
    doppler: float | None,
    lli: int,
    config: HatchConfig,
) -> str | None:
    """Why this satellite's smoothing must restart at this epoch (None: it continues, or starts)."""
    if track is None:
        return None
    dt = t - track.t
    if lli & 1:
        return "loss of lock (lli bit 0)"
    if not 0.0 < dt <= config.max_gap_s:
        return f"{dt:g} s since its previous carrier phase (max gap {config.max_gap_s:g} s)"
    change = cycles - track.phase_cycles
    if doppler is not None or track.doppler_hz is not None:
        rates = [d for d in (track.doppler_hz, doppler) if d is not None]
        predicted = -sum(rates) / len(rates) * dt
        if abs(change - predicted) > config.slip_cycles_per_s * dt:
            return f"phase change {change - predicted:+.1f} cycles off the Doppler's over {dt:g} s"
    jump = code - (track.smoothed_m + lam * change)
    if abs(jump) > config.code_jump_m:
        return f"code-carrier jump of {jump:+.1f} m"
    return None


class CarrierTable:
    """Every satellite's smoothing as arrays: the satellite ids and a (k, 6) table of their tracks
    (:data:`_COLUMNS`'s fields), in the order they were written; the session keeps and stores the arrays as
    they are (the compiled update, pipelines/gnss_carrier_kernel.py, reads and writes them: no objects per
    satellite). :meth:`tracks` is the numpy reference's view (:func:`hatch_update` on a dict)."""

    __slots__ = ("sats", "table")

    def __init__(self, sats: Sequence[str] = (), table: np.ndarray | None = None) -> None:
        self.sats = tuple(sats)
        self.table: np.ndarray = np.zeros((0, _COLUMNS)) if table is None else table
        if self.table.shape != (len(self.sats), _COLUMNS):
            raise ValueError(f"{len(self.sats)} satellites, table {self.table.shape}")

    def __len__(self) -> int:
        return len(self.sats)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, CarrierTable):
            return NotImplemented
        return self.sats == other.sats and np.array_equal(self.table, other.table)

    __hash__ = None  # type: ignore[assignment]

    def tracks(self) -> dict[str, CarrierTrack]:
        """The tracks by satellite (a new dict)."""
        return tracks_from_arrays(self.sats, self.table)

    @classmethod
    def from_tracks(cls, tracks: dict[str, CarrierTrack]) -> CarrierTable:
        """The table of ``tracks`` (sorted by satellite)."""
        return cls(*tracks_to_arrays(tracks))

    def rows(self, sats: Sequence[str]) -> np.ndarray:
        """Per satellite of ``sats``, its row of the table (-1: none)."""
        where = {s: k for k, s in enumerate(self.sats)}
        return np.array([where.get(s, -1) for s in sats], dtype=np.int64)


def tracks_to_arrays(tracks: dict[str, CarrierTrack]) -> tuple[list[str], np.ndarray]:
    """The tracks as satellite ids and a (k, 6) float table, for the session's exact byte form."""
    sats = sorted(tracks)
    rows = [
        (
            track.t,
            track.count,
            track.smoothed_m,
            track.phase_cycles,
            0.0 if track.doppler_hz is None else track.doppler_hz,
            float(track.doppler_hz is not None),
        )
        for track in (tracks[sat] for sat in sats)
    ]
    return sats, np.array(rows, dtype=float).reshape(len(sats), _COLUMNS)


def tracks_from_arrays(sats: Sequence[str], table: np.ndarray) -> dict[str, CarrierTrack]:
    """Inverse of :func:`tracks_to_arrays`."""
    rows = (
        np.asarray(table, dtype=float).reshape(len(sats), _COLUMNS).tolist()
    )  # Python floats, the same values
    return {
        str(sat): new_track(row[0], row[1], row[2], row[3], row[4] if row[5] else None)
        for sat, row in zip(sats, rows, strict=True)
    }
