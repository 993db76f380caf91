"""RINEX 3 navigation reader: Keplerian broadcast ephemerides (GPS, BeiDou, Galileo, QZSS) and header corrections.

Follows the RINEX 3.04 format description: a header of 80-column labelled lines ended by ``END OF HEADER``,
then records of a first line (satellite, epoch of clock, three clock terms) and "broadcast orbit" lines of four
D19.12 fields starting at column 5. Numbers may use a Fortran ``D`` exponent and fields may be blank. GLONASS
and SBAS records (state-vector ephemerides) are recognised and skipped. All times are converted to continuous
GPS seconds (see :mod:`edgepos.gnss.timesys`); BeiDou epochs, which RINEX gives in BDT, gain 14 s.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from edgepos.gnss.timesys import (
    SECONDS_PER_WEEK,
    bdt_to_gpst,
    bdt_week_to_gpst,
    calendar_to_seconds,
    from_week_seconds,
)

KEPLER_SYSTEMS = frozenset("GCEJ")
"""Systems whose broadcast ephemeris is Keplerian (8-line records in RINEX 3)."""

_RECORD_START = re.compile(r"^[GCEJRSI][ 0-9][0-9] \d{4} ")


class RinexError(ValueError):
    """Malformed RINEX input; the message names the file line (1-based) and what is wrong with it."""

    def __init__(self, line_number: int, message: str) -> None:
        super().__init__(f"line {line_number}: {message}")
        self.line_number = line_number


@dataclass(frozen=True)
class KeplerEphemeris:
    """One broadcast Keplerian ephemeris (IS-GPS-200 LNAV, BDS-SIS-ICD D1/D2, Galileo OS-SIS-ICD).

    Angles are radians, rates rad/s, lengths metres, times seconds. ``toc`` and ``toe`` are continuous GPS
    seconds (BeiDou's BDT values converted); ``toe_sow`` is the time of ephemeris in the satellite system's
    own seconds of week, which the BeiDou and GPS longitude-of-node formula uses.
    ``tgd1``/``tgd2``: GPS TGD / 0; BeiDou TGD1 (B1I) / TGD2 (B2I); Galileo BGD E5b-E1 / BGD E5a-E1 (seconds).
    """

    system: str
    prn: int
    toc: float
    af0: float
    af1: float
    af2: float
    iode: float
    crs: float
    delta_n: float
    m0: float
    cuc: float
    e: float
    cus: float
    sqrt_a: float
    toe: float
    toe_sow: float
    cic: float
    omega0: float
    cis: float
    i0: float
    crc: float
    omega: float
    omega_dot: float
    idot: float
    week: int
    accuracy_m: float
    health: int
    tgd1: float
    tgd2: float
    transmit_time: float
    fit_interval_s: float
    data_sources: int = 0

    @property
    def sat(self) -> str:
        """RINEX satellite identifier, e.g. ``G05``."""
        return f"{self.system}{self.prn:02d}"


@dataclass(frozen=True)
class NavigationData:
    """A parsed navigation file: header corrections plus the Keplerian ephemerides in file order."""

    version: float
    ionosphere: dict[str, tuple[float, float, float, float]]
    """Header ``IONOSPHERIC CORR`` sets by type: ``GPSA``/``GPSB`` Klobuchar alpha (s, s/sc, s/sc^2, s/sc^3)
    and beta (s, ...); ``BDSA``/``BDSB`` likewise; ``GAL`` NeQuick ai0..ai2 (and a zero)."""
    leap_seconds: int | None
    ephemerides: tuple[KeplerEphemeris, ...]
    skipped: dict[str, int] = field(default_factory=dict)
    """Records of systems without a Keplerian ephemeris (GLONASS, SBAS), counted by system letter."""

    @property
    def klobuchar_gps(self) -> tuple[tuple[float, ...], tuple[float, ...]] | None:
        """(alpha, beta) of the GPS Klobuchar model when the header carries both, else None."""
        if "GPSA" in self.ionosphere and "GPSB" in self.ionosphere:
            return self.ionosphere["GPSA"], self.ionosphere["GPSB"]
        return None


def _number(text: str, line_number: int, what: str) -> float:
    """A RINEX real (``D`` or ``E`` exponent); blank -> NaN so callers decide whether it is optional."""
    stripped = text.strip()
    if not stripped:
        return math.nan
    try:
        return float(stripped.replace("D", "E").replace("d", "e"))
    except ValueError:
        raise RinexError(line_number, f"{what}: cannot read number {stripped!r}") from None


def _orbit_fields(line: str, line_number: int) -> list[float]:
    """The four D19.12 fields of a broadcast-orbit line (columns 5-80)."""
    padded = line.ljust(80)
    return [_number(padded[4 + 19 * k : 23 + 19 * k], line_number, f"orbit field {k + 1}") for k in range(4)]


def _parse_header(
    lines: list[str],
) -> tuple[int, float, dict[str, tuple[float, float, float, float]], int | None]:
    """Header -> (index of the first data line, version, ionosphere sets, leap seconds)."""
    if not lines or "RINEX VERSION / TYPE" not in lines[0]:
        raise RinexError(1, "first line must be the 'RINEX VERSION / TYPE' header line")
    version = _number(lines[0][:9], 1, "RINEX version")
    if not 3.0 <= version < 4.0:
        raise RinexError(1, f"RINEX version {version} not supported (3.xx only)")
    if lines[0][20:21] != "N":
        raise RinexError(1, f"file type {lines[0][20:21]!r} is not 'N' (navigation data)")
    ionosphere: dict[str, tuple[float, float, float, float]] = {}
    leap: int | None = None
    for index, line in enumerate(lines):
        label = line[60:].strip()
        number = index + 1
        if label == "END OF HEADER":
            return index + 1, version, ionosphere, leap
        if label == "IONOSPHERIC CORR":
            kind = line[:4].strip()
            values = [
                _number(line[5 + 12 * k : 17 + 12 * k], number, f"{kind} coefficient {k}") for k in range(4)
            ]
            if any(math.isnan(v) for v in values):
                raise RinexError(number, f"IONOSPHERIC CORR {kind}: blank coefficient")
            ionosphere[kind] = (values[0], values[1], values[2], values[3])
        elif label == "LEAP SECONDS":
            try:
                leap = int(line[:6])
            except ValueError:
                raise RinexError(number, f"LEAP SECONDS: cannot read {line[:6]!r}") from None
    raise RinexError(len(lines), "no 'END OF HEADER' line")


def _epoch(line: str, number: int) -> float:
    """Seconds since 1980-01-06 of the record's epoch of clock, in the record's own time scale."""
    try:
        year, month, day = int(line[4:8]), int(line[9:11]), int(line[12:14])
        hour, minute, second = int(line[15:17]), int(line[18:20]), int(line[21:23])
        return calendar_to_seconds(year, month, day, hour, minute, second)
    except ValueError:
        raise RinexError(number, f"bad epoch {line[4:23]!r}") from None


def _kepler_record(lines: list[str], first_number: int) -> KeplerEphemeris:
    """Eight lines of a GPS/BeiDou/Galileo/QZSS record -> ephemeris (validated)."""
    head = lines[0].ljust(80)
    system = head[0]
    try:
        prn = int(head[1:3])
    except ValueError:
        raise RinexError(first_number, f"bad satellite number {head[1:3]!r}") from None
    epoch = _epoch(head, first_number)
    clock = [_number(head[23 + 19 * k : 42 + 19 * k], first_number, f"clock field {k + 1}") for k in range(3)]
    orbit: list[float] = []
    for offset, line in enumerate(lines[1:], start=1):
        if line[:4].strip():
            raise RinexError(first_number + offset, "broadcast-orbit line must start with four blanks")
        orbit.extend(_orbit_fields(line, first_number + offset))
    required = {
        "af0": clock[0],
        "af1": clock[1],
        "af2": clock[2],
        "Crs": orbit[1],
        "Delta n": orbit[2],
        "M0": orbit[3],
        "Cuc": orbit[4],
        "e": orbit[5],
        "Cus": orbit[6],
        "sqrt(A)": orbit[7],
        "Toe": orbit[8],
        "Cic": orbit[9],
        "OMEGA0": orbit[10],
        "Cis": orbit[11],
        "i0": orbit[12],
        "Crc": orbit[13],
        "omega": orbit[14],
        "OMEGA DOT": orbit[15],
        "IDOT": orbit[16],
        "week": orbit[18],
    }
    line_of = {
        "af0": 0,
        "af1": 0,
        "af2": 0,
        "Crs": 1,
        "Delta n": 1,
        "M0": 1,
        "Cuc": 2,
        "e": 2,
        "Cus": 2,
        "sqrt(A)": 2,
        "Toe": 3,
        "Cic": 3,
        "OMEGA0": 3,
        "Cis": 3,
        "i0": 4,
        "Crc": 4,
        "omega": 4,
        "OMEGA DOT": 4,
        "IDOT": 5,
        "week": 5,
    }
    for name, value in required.items():
        if not math.isfinite(value):
            raise RinexError(first_number + line_of[name], f"{system}{prn:02d}: field {name} is blank")
    if not 0.0 <= orbit[5] < 1.0:
        raise RinexError(first_number + 2, f"{system}{prn:02d}: eccentricity {orbit[5]} outside [0, 1)")
    if orbit[7] <= 0.0:
        raise RinexError(first_number + 2, f"{system}{prn:02d}: sqrt(A) {orbit[7]} must be positive")

    def optional(value: float, default: float = 0.0) -> float:
        return default if math.isnan(value) else value

    week = int(orbit[18])
    toe_sow = orbit[8]
    if system == "C":
        toc = bdt_to_gpst(epoch)
        toe = bdt_week_to_gpst(week, toe_sow)
        tgd1, tgd2 = optional(orbit[22]), optional(orbit[23])
        fit = 7200.0
        transmit = bdt_week_to_gpst(week, optional(orbit[24], toe_sow))
    else:
        toc = epoch
        toe = from_week_seconds(week, toe_sow)
        if system == "E":
            tgd1, tgd2 = optional(orbit[23]), optional(orbit[22])
            fit = 4.0 * 3600.0
        else:
            tgd1, tgd2 = optional(orbit[22]), 0.0
            hours = optional(orbit[25], 0.0)
            fit = (hours if hours > 0.0 else 4.0) * 3600.0
        transmit = from_week_seconds(week, optional(orbit[24], toe_sow))
    # The week field goes with Toe; the clock epoch may sit across a week boundary from it.
    toe += SECONDS_PER_WEEK * round((toc - toe) / SECONDS_PER_WEEK)
    return KeplerEphemeris(
        system=system,
        prn=prn,
        toc=toc,
        af0=clock[0],
        af1=clock[1],
        af2=clock[2],
        iode=optional(orbit[0]),
        crs=orbit[1],
        delta_n=orbit[2],
        m0=orbit[3],
        cuc=orbit[4],
        e=orbit[5],
        cus=orbit[6],
        sqrt_a=orbit[7],
        toe=toe,
        toe_sow=toe_sow,
        cic=orbit[9],
        omega0=orbit[10],
        cis=orbit[11],
        i0=orbit[12],
        crc=orbit[13],
        omega=orbit[14],
        omega_dot=orbit[15],
        idot=orbit[16],
        week=week,
        accuracy_m=optional(orbit[20], math.nan),
        health=int(optional(orbit[21])),
        tgd1=tgd1,
        tgd2=tgd2,
        transmit_time=transmit,
        fit_interval_s=fit,
        data_sources=int(optional(orbit[17])) if system == "E" else 0,
    )


def _records(lines: list[str], start: int) -> Iterator[tuple[int, list[str]]]:
    """Split the data section into (first line index, lines) per record."""
    index = start
    while index < len(lines):
        line = lines[index]
        if not line.strip():
            index += 1
            continue
        if not _RECORD_START.match(line):
            raise RinexError(index + 1, f"expected a record start like 'G05 2020 ...', got {line[:23]!r}")
        end = index + 1
        while end < len(lines) and lines[end].startswith("    ") and not _RECORD_START.match(lines[end]):
            end += 1
        yield index, lines[index:end]
        index = end


def parse_navigation(lines: Iterable[str]) -> NavigationData:
    """Parse RINEX 3 navigation text (lines without or with newlines) into ephemerides and header data."""
    text = [line.rstrip("\r\n") for line in lines]
    start, version, ionosphere, leap = _parse_header(text)
    ephemerides: list[KeplerEphemeris] = []
    skipped: Counter[str] = Counter()
    for index, record in _records(text, start):
        system = record[0][0]
        if system not in KEPLER_SYSTEMS:
            skipped[system] += 1
            continue
        if len(record) != 8:
            raise RinexError(index + 1, f"{record[0][:3]} record has {len(record)} lines, expected 8")
        ephemerides.append(_kepler_record(record, index + 1))
    return NavigationData(version, ionosphere, leap, tuple(ephemerides), dict(skipped))


def read_navigation(path: str | Path) -> NavigationData:
    """Read a RINEX 3 navigation file from disk."""
    with open(path, encoding="ascii", errors="replace") as handle:
        return parse_navigation(handle)
