"""RINEX 3 observation reader, streaming epoch by epoch, keeping only the observation codes asked for.

RINEX 3.04 layout: the header lists each system's observation types (``SYS / # / OBS TYPES``, 13 per line
with continuation lines); each epoch starts with ``>`` (date, epoch flag, satellite count) followed by one line
per satellite: the satellite id (3 characters) and per type a 16-character field (F14.3 value, loss-of-lock
indicator, signal strength). Blank fields are missing observations (NaN here). Besides the chosen
pseudorange and C/N0, the reader keeps the Doppler (D) and carrier phase (L, cycles, with its loss-of-lock
indicator) of the pseudorange's own signal. Event records (flags 2-5) and
cycle-slip records (flag 6) are skipped. Epoch times are returned as continuous GPS seconds.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from edgepos.gnss.rinex_nav import RinexError
from edgepos.gnss.timesys import BDT_MINUS_GPST_S, calendar_to_seconds

DEFAULT_CODES: dict[str, tuple[str, str]] = {"G": ("C1C", "S1C"), "C": ("C2I", "S2I"), "E": ("C1C", "S1C")}
"""Per system (pseudorange code, C/N0 code): GPS L1 C/A, BeiDou B1I, Galileo E1."""
ALL_SYSTEMS = "".join(DEFAULT_CODES)
"""Every constellation read by default: all those with a signal above (GLONASS, SBAS and QZSS are not used)."""


def parse_systems(text: str) -> str:
    """RINEX system letters such as ``GCE``; ValueError naming any this project cannot use."""
    unknown = sorted({letter for letter in text if letter not in DEFAULT_CODES})
    if unknown or not text:
        raise ValueError(
            f"constellations must be letters of {ALL_SYSTEMS} (G GPS, C BeiDou, E Galileo), got {text!r}"
            + (f": {''.join(unknown)} not supported" if unknown else "")
        )
    return "".join(dict.fromkeys(text))  # each once, in the order given


def doppler_code(code: str) -> str:
    """The Doppler observation of the same signal as a pseudorange code (``C1C`` -> ``D1C``)."""
    return "D" + code[1:]


def carrier_code(code: str) -> str:
    """The carrier-phase observation of the same signal as a pseudorange code (``C1C`` -> ``L1C``)."""
    return "L" + code[1:]


@dataclass(frozen=True)
class ObservationHeader:
    """What the reader needs from the header."""

    version: float
    obs_types: dict[str, tuple[str, ...]]
    time_system: str
    approx_position: tuple[float, float, float] | None
    interval_s: float | None
    antenna_delta_hen: tuple[float, float, float] | None = None
    """``ANTENNA: DELTA H/E/N`` (m): the antenna reference point above, east and north of the marker, whose
    position ``APPROX POSITION XYZ`` gives."""


@dataclass(frozen=True)
class ObservationEpoch:
    """Observations of one epoch for the satellites that have every requested code of their system.

    ``systems`` and ``prns`` identify the satellites, in file order; ``doppler_hz`` is the D observation of
    the pseudorange's own signal (RINEX sign: positive when the satellite approaches), NaN when the header
    lacks it or the field is blank. ``carrier_cycles`` is the L observation of the same signal (cycles, NaN
    when absent or blank) and ``lli`` its loss-of-lock indicator digit (RINEX 3: bit 0 set when lock was lost
    since the previous observation, so the phase may have slipped; bit 1 half-cycle ambiguity; 0 when blank).
    """

    gpst: float
    flag: int
    line_number: int
    systems: tuple[str, ...]
    prns: np.ndarray
    pseudorange_m: np.ndarray
    cn0_dbhz: np.ndarray
    doppler_hz: np.ndarray
    carrier_cycles: np.ndarray
    lli: np.ndarray

    @property
    def sats(self) -> tuple[str, ...]:
        """RINEX satellite identifiers of the satellites in this epoch."""
        return tuple(f"{s}{int(p):02d}" for s, p in zip(self.systems, self.prns))

    def __len__(self) -> int:
        return len(self.systems)


def _parse_header(lines: Iterator[str]) -> tuple[ObservationHeader, int]:
    """Consume the header; return it and the number of lines consumed."""
    first = next(lines, None)
    if first is None or "RINEX VERSION / TYPE" not in first:
        raise RinexError(1, "first line must be the 'RINEX VERSION / TYPE' header line")
    try:
        version = float(first[:9])
    except ValueError:
        raise RinexError(1, f"cannot read RINEX version {first[:9]!r}") from None
    if not 3.0 <= version < 4.0:
        raise RinexError(1, f"RINEX version {version} not supported (3.xx only)")
    if first[20:21] != "O":
        raise RinexError(1, f"file type {first[20:21]!r} is not 'O' (observation data)")
    obs_types: dict[str, list[str]] = {}
    expected: dict[str, tuple[int, int]] = {}
    current: str | None = None
    time_system = "GPS"
    approx: tuple[float, float, float] | None = None
    delta: tuple[float, float, float] | None = None
    interval: float | None = None
    number = 1
    for line in lines:
        number += 1
        label = line[60:].strip()
        if label == "END OF HEADER":
            for system, (count, declared_at) in expected.items():
                if len(obs_types[system]) != count:
                    raise RinexError(
                        declared_at,
                        f"system {system}: {len(obs_types[system])} observation types, header said {count}",
                    )
            header = ObservationHeader(
                version, {k: tuple(v) for k, v in obs_types.items()}, time_system, approx, interval, delta
            )
            return header, number
        if label == "SYS / # / OBS TYPES":
            if line[0] != " ":
                current = line[0]
                try:
                    expected[current] = (int(line[3:6]), number)
                except ValueError:
                    raise RinexError(number, f"bad observation type count {line[3:6]!r}") from None
                obs_types[current] = []
            elif current is None:
                raise RinexError(number, "observation type continuation line before any system line")
            obs_types[current].extend(line[7:60].split())
        elif label == "TIME OF FIRST OBS":
            time_system = line[48:51].strip() or "GPS"
        elif label == "APPROX POSITION XYZ":
            try:
                approx = (float(line[0:14]), float(line[14:28]), float(line[28:42]))
            except ValueError:
                raise RinexError(number, "cannot read APPROX POSITION XYZ") from None
        elif label == "ANTENNA: DELTA H/E/N":
            try:
                delta = (float(line[0:14]), float(line[14:28]), float(line[28:42]))
            except ValueError:
                raise RinexError(number, "cannot read ANTENNA: DELTA H/E/N") from None
        elif label == "INTERVAL":
            try:
                interval = float(line[:10])
            except ValueError:
                raise RinexError(number, "cannot read INTERVAL") from None
    raise RinexError(number, "no 'END OF HEADER' line")


def _field(line: str, index: int) -> float:
    """Value of observation ``index`` (0-based) on a satellite line; NaN when blank or beyond the line."""
    start = 3 + 16 * index
    text = line[start : start + 14].strip()
    return float(text) if text else math.nan


def _lli(line: str, index: int) -> int:
    """Loss-of-lock indicator digit of observation ``index`` (0 when blank or beyond the line)."""
    text = line[3 + 16 * index + 14 : 3 + 16 * index + 15].strip()
    return int(text) if text else 0


def _time_offset(time_system: str) -> float:
    """Seconds to add to the file's epoch times to obtain GPS time."""
    if time_system in ("GPS", "GAL"):
        return 0.0
    if time_system == "BDT":
        return -BDT_MINUS_GPST_S
    raise RinexError(1, f"observation time system {time_system!r} not supported (GPS, GAL or BDT)")


def iter_epochs(
    lines: Iterable[str], codes: Mapping[str, tuple[str, str]] | None = None
) -> Iterator[tuple[ObservationHeader, ObservationEpoch]]:
    """Stream (header, epoch) pairs from RINEX 3 observation text.

    ``codes`` maps a system letter to its (pseudorange, C/N0) observation codes; systems not in it are
    dropped, as are satellites whose pseudorange field is blank. A C/N0 code absent from the header gives NaN,
    as does the Doppler of the pseudorange's signal (:func:`doppler_code`) and its carrier phase
    (:func:`carrier_code`, with its loss-of-lock indicator, 0 when blank) when absent or blank.
    An explicitly requested pseudorange code that the header does not list for a present system is an error;
    with the defaults such a system is dropped.
    """
    explicit = codes is not None
    chosen = dict(DEFAULT_CODES if codes is None else codes)
    stream = (line.rstrip("\r\n") for line in lines)
    header, number = _parse_header(stream)
    offset = _time_offset(header.time_system)
    columns: dict[str, tuple[int, int | None, int | None, int | None]] = {}
    for system, (code, cn0_code) in chosen.items():
        types = header.obs_types.get(system)
        if types is None:
            continue
        if code not in types:
            if explicit:
                raise RinexError(
                    number, f"system {system} has no observation {code!r}; header lists {', '.join(types)}"
                )
            continue
        doppler_type, carrier_type = doppler_code(code), carrier_code(code)
        columns[system] = (
            types.index(code),
            types.index(cn0_code) if cn0_code in types else None,
            types.index(doppler_type) if doppler_type in types else None,
            types.index(carrier_type) if carrier_type in types else None,
        )
    for line in stream:
        number += 1
        if not line.strip():
            continue
        if not line.startswith(">"):
            raise RinexError(number, f"expected an epoch line starting with '>', got {line[:20]!r}")
        try:
            flag = int(line[31:32])
            count = int(line[32:35])
        except ValueError:
            raise RinexError(number, f"bad epoch flag or satellite count in {line.strip()!r}") from None
        if flag > 1:
            for _ in range(count):
                if next(stream, None) is None:
                    raise RinexError(number, "file ends inside an event record")
                number += 1
            continue
        try:
            t = (
                calendar_to_seconds(
                    int(line[2:6]),
                    int(line[7:9]),
                    int(line[10:12]),
                    int(line[13:15]),
                    int(line[16:18]),
                    float(line[18:29]),
                )
                + offset
            )
        except ValueError:
            raise RinexError(number, f"bad epoch time {line[2:29]!r}") from None
        epoch_line = number
        systems: list[str] = []
        prns: list[int] = []
        ranges: list[float] = []
        cn0s: list[float] = []
        dopplers: list[float] = []
        carriers: list[float] = []
        llis: list[int] = []
        for _ in range(count):
            sat_line = next(stream, None)
            number += 1
            if sat_line is None:
                raise RinexError(
                    number, f"file ends inside the epoch of line {epoch_line} ({count} satellites announced)"
                )
            if sat_line.startswith(">"):
                raise RinexError(
                    number, f"epoch of line {epoch_line} announced {count} satellites, found fewer"
                )
            system = sat_line[0]
            if system not in columns:
                continue
            try:
                prn = int(sat_line[1:3])
                value = _field(sat_line, columns[system][0])
                cn0_index = columns[system][1]
                cn0 = _field(sat_line, cn0_index) if cn0_index is not None else math.nan
                doppler_index = columns[system][2]
                doppler = _field(sat_line, doppler_index) if doppler_index is not None else math.nan
                carrier_index = columns[system][3]
                carrier = _field(sat_line, carrier_index) if carrier_index is not None else math.nan
                lli = (
                    _lli(sat_line, carrier_index)
                    if carrier_index is not None and math.isfinite(carrier)
                    else 0
                )
            except ValueError:
                raise RinexError(number, f"cannot read observation of {sat_line[:3]!r}") from None
            if math.isnan(value) or value <= 0.0:
                continue
            systems.append(system)
            prns.append(prn)
            ranges.append(value)
            cn0s.append(cn0)
            dopplers.append(doppler)
            carriers.append(carrier)
            llis.append(lli)
        yield (
            header,
            ObservationEpoch(
                t,
                flag,
                epoch_line,
                tuple(systems),
                np.asarray(prns, dtype=int),
                np.asarray(ranges, dtype=float),
                np.asarray(cn0s, dtype=float),
                np.asarray(dopplers, dtype=float),
                np.asarray(carriers, dtype=float),
                np.asarray(llis, dtype=int),
            ),
        )


def read_header(path: str | Path) -> ObservationHeader:
    """Just the header of a RINEX 3 observation file."""
    with open(path, encoding="ascii", errors="replace") as handle:
        return _parse_header(line.rstrip("\r\n") for line in handle)[0]


def read_epochs(
    path: str | Path, codes: Mapping[str, tuple[str, str]] | None = None
) -> Iterator[ObservationEpoch]:
    """Stream the epochs of a RINEX 3 observation file (the file stays open while iterating)."""
    with open(path, encoding="ascii", errors="replace") as handle:
        for _, epoch in iter_epochs(handle, codes):
            yield epoch
