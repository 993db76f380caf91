"""A reference station's RTCM 3 stream as observation epochs: MSM4 and MSM7 pseudoranges and the station's
antenna reference point (messages 1005/1006). The bits are decoded by ``pyrtcm``; this module only frames the
stream, checks which messages it holds and turns their fields into metres and GPS seconds.

Framing (RTCM 10403.3, 4): a frame is the preamble 0xD3, 6 reserved bits and a 10-bit payload length, the
payload, and a 24-bit CRC. Each frame is handed to ``pyrtcm`` whole, which checks the CRC and decodes it.

MSM pseudoranges: (DF397 integer ms + DF398 rough ms fraction + DF400 / DF405 fine ms) times c / 1000; a
satellite whose DF397 is 255 or a cell whose fine pseudorange holds the "invalid" value is left out. Only the
signal the project uses per system (``rinex_obs.DEFAULT_CODES``: GPS 1C, BeiDou 2I, Galileo 1C) is kept, so
the corrections match what a rover's pseudoranges are. GLONASS, SBAS, QZSS and NavIC MSMs are accepted and
skipped (the positioning code does not use those systems).

MSM times are times of week (ms): GPS and Galileo in GPS time, BeiDou in BDT (14 s behind GPS time). The week
is not in the stream: ``week_of`` resolves a time of week to continuous GPS seconds (the service uses the
week that puts it nearest the loaded ephemerides' validity window). Messages of one epoch (the MSMs of each
system, same GPS time) form one :class:`ObservationEpoch`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from pyrtcm import RTCMMessage, RTCMReader
from pyrtcm.exceptions import RTCMMessageError, RTCMParseError, RTCMTypeError
from pyrtcm.rtcmhelpers import parse_msm

from edgepos.gnss.orbits import SPEED_OF_LIGHT
from edgepos.gnss.rinex_obs import DEFAULT_CODES, ObservationEpoch
from edgepos.gnss.timesys import BDT_MINUS_GPST_S

PREAMBLE = 0xD3
MSM4 = {"1074": "G", "1094": "E", "1124": "C"}
MSM7 = {"1077": "G", "1097": "E", "1127": "C"}
SKIPPED_MSM = frozenset(f"{base + kind}" for base in (1080, 1100, 1110, 1130) for kind in (4, 5, 6, 7))
"""MSM4-7 of GLONASS, SBAS, QZSS and NavIC: valid, but of systems the positioning code does not use."""
POSITION_MESSAGES = ("1005", "1006")
SKIPPED_OTHER = frozenset(
    ("1007", "1008", "1013", "1019", "1020", "1033", "1041", "1042", "1044", "1045", "1046", "1230")
)
"""Messages a station's stream carries beside its observations and that corrections do not need: antenna
and receiver descriptors, system parameters, broadcast ephemerides (the service uses the uploaded navigation
file) and GLONASS code-phase biases. Counted and skipped; any other type is refused (legacy 1001-1004 and
1009-1012 observations among them: send MSM4 or MSM7)."""
_INVALID_FINE_MS = -(2.0**-10)
"""The "invalid" value of DF400 (-2^14 x 2^-24 ms) and of DF405 (-2^19 x 2^-29 ms) after pyrtcm's scaling."""
_MS_TO_M = SPEED_OF_LIGHT / 1000.0


class RtcmError(ValueError):
    """A frame that does not parse, or a message this service does not accept; ``message`` names it
    (e.g. ``"frame 3 (message 1077, bytes 412-633)"``)."""

    def __init__(self, message: str, reason: str) -> None:
        super().__init__(f"{message}: {reason}")
        self.message = message
        self.reason = reason


@dataclass(frozen=True)
class RtcmContent:
    """What a stream of frames held: observation epochs (in time order), the antenna reference point of the
    last 1005/1006 (ECEF m, None without one), and how many frames of each message type were read."""

    epochs: tuple[ObservationEpoch, ...]
    position: tuple[float, float, float] | None
    counts: Mapping[str, int]


def frames(data: bytes) -> list[tuple[int, bytes]]:
    """Split a byte stream into (offset, frame) pairs; RtcmError where something else than a frame begins
    or a frame is cut short."""
    found: list[tuple[int, bytes]] = []
    offset = 0
    while offset < len(data):
        name = f"frame {len(found) + 1} (at byte {offset})"
        if data[offset] != PREAMBLE:
            raise RtcmError(name, f"expected the RTCM 3 preamble 0xD3, got 0x{data[offset]:02X}")
        if offset + 3 > len(data):
            raise RtcmError(name, "the stream ends inside the frame header")
        length = ((data[offset + 1] & 0x03) << 8) | data[offset + 2]
        end = offset + 3 + length + 3
        if end > len(data):
            raise RtcmError(name, f"the stream ends inside the frame ({length}-byte payload announced)")
        found.append((offset, data[offset:end]))
        offset = end
    return found


def _message_type(frame: bytes) -> str:
    if len(frame) < 8:
        return "?"
    return str((frame[3] << 4) | (frame[4] >> 4))


def parse_frame(index: int, offset: int, frame: bytes) -> RTCMMessage:
    """One frame decoded by pyrtcm (CRC checked); RtcmError naming the frame and its message type."""
    kind = _message_type(frame)
    name = f"frame {index} (message {kind}, bytes {offset}-{offset + len(frame) - 1})"
    try:
        message = RTCMReader.parse(frame)
    except (RTCMParseError, RTCMMessageError, RTCMTypeError, ValueError, KeyError, IndexError) as error:
        raise RtcmError(name, str(error) or type(error).__name__) from None
    if getattr(message, "identity", None) is None:
        raise RtcmError(name, "pyrtcm does not know this message type")
    return message


def _cells(message: RTCMMessage, system: str, msm7: bool) -> list[tuple[int, float, float]]:
    """(PRN, pseudorange m, C/N0 dB-Hz) of every valid cell of the system's pseudorange signal."""
    parsed = parse_msm(message)
    if parsed is None:
        return []
    _, sats, cells = parsed
    signal = DEFAULT_CODES[system][0][1:]
    rough = {int(sat["PRN"]): (sat.get("DF397"), sat.get("DF398")) for sat in sats}
    out = []
    for cell in cells:
        if cell.get("CELLSIG") != signal:
            continue
        prn = int(cell["CELLPRN"])
        whole_ms, fraction_ms = rough.get(prn, (None, None))
        fine_ms = cell.get("DF405" if msm7 else "DF400")
        if whole_ms is None or whole_ms == 255 or fraction_ms is None or fine_ms is None:
            continue
        if math.isclose(fine_ms, _INVALID_FINE_MS, rel_tol=0.0, abs_tol=1e-15):
            continue
        cn0 = cell.get("DF408" if msm7 else "DF403")
        pseudorange = (whole_ms + fraction_ms + fine_ms) * _MS_TO_M
        out.append((prn, pseudorange, float(cn0) if cn0 else math.nan))
    return out


def decode(data: bytes, gpst_of_week: Callable[[float], float]) -> RtcmContent:
    """Frames -> epochs and station position. ``gpst_of_week`` maps a GPS time of week (s) to continuous
    GPS seconds (the week comes from outside the stream). RtcmError for a frame that does not parse or a
    message type that is neither an accepted MSM, a skipped system's MSM nor 1005/1006."""
    by_time: dict[float, dict[tuple[str, int], tuple[float, float]]] = {}
    position: tuple[float, float, float] | None = None
    counts: dict[str, int] = {}
    for index, (offset, frame) in enumerate(frames(data), start=1):
        message = parse_frame(index, offset, frame)
        kind = str(message.identity)
        counts[kind] = counts.get(kind, 0) + 1
        if kind in POSITION_MESSAGES:
            position = (float(message.DF025), float(message.DF026), float(message.DF027))
            continue
        if kind in SKIPPED_MSM or kind in SKIPPED_OTHER:
            continue
        system = MSM4.get(kind) or MSM7.get(kind)
        if system is None:
            name = f"frame {index} (message {kind}, bytes {offset}-{offset + len(frame) - 1})"
            accepted = ", ".join([*MSM4, *MSM7, *POSITION_MESSAGES])
            raise RtcmError(
                name,
                f"message type {kind} is not accepted here (observations: {accepted}; GLONASS, SBAS, QZSS "
                "and NavIC MSMs and descriptor, ephemeris and bias messages are skipped)",
            )
        tow_ms = float(
            message.DF427 if system == "C" else (message.DF248 if system == "E" else message.DF004)
        )
        tow = tow_ms / 1000.0 - (BDT_MINUS_GPST_S if system == "C" else 0.0)
        gpst = round(gpst_of_week(tow % 604800.0), 3)
        rows = by_time.setdefault(gpst, {})
        for prn, pseudorange, cn0 in _cells(message, system, kind in MSM7):
            rows.setdefault((system, prn), (pseudorange, cn0))  # the first message of a satellite counts
    epochs = []
    for gpst in sorted(by_time):
        epoch_rows = [(sat[0], sat[1], *values) for sat, values in sorted(by_time[gpst].items())]
        if not epoch_rows:
            continue
        count = len(epoch_rows)
        nan = np.full(count, np.nan)
        epochs.append(
            ObservationEpoch(
                gpst=gpst,
                flag=0,
                line_number=0,
                systems=tuple(row[0] for row in epoch_rows),
                prns=np.array([row[1] for row in epoch_rows], dtype=int),
                pseudorange_m=np.array([row[2] for row in epoch_rows]),
                cn0_dbhz=np.array([row[3] for row in epoch_rows]),
                doppler_hz=nan,
                carrier_cycles=nan.copy(),
                lli=np.zeros(count, dtype=int),
            )
        )
    return RtcmContent(tuple(epochs), position, counts)
