"""RTCM 3 frames for the tests: MSM4/MSM7 (one signal per satellite) and 1005 encoded from values by
RTCM 10403.3's bit layouts, framed and CRC-ed with pyrtcm (``RTCMMessage(payload=...).serialize()``).
pyrtcm has no encoder for these messages' fields, so the bits are written here; the service decodes
them with pyrtcm, which makes every test a round trip through an independent decoder."""

from __future__ import annotations

from collections.abc import Sequence

from edgepos.gnss.orbits import SPEED_OF_LIGHT
from pyrtcm import RTCMMessage

MS_M = SPEED_OF_LIGHT / 1000.0
SIGNAL_ID = {"G": 2, "E": 2, "C": 2}
"""MSM signal ids of GPS L1 C/A (1C), Galileo E1 C (1C) and BeiDou B1I (2I)."""
MESSAGE_BASE = {"G": 1070, "E": 1090, "C": 1120}


class Bits:
    def __init__(self) -> None:
        self.value = 0
        self.size = 0

    def put(self, value: int, width: int) -> None:
        self.value = (self.value << width) | (value & ((1 << width) - 1))
        self.size += width

    def payload(self) -> bytes:
        pad = (-self.size) % 8
        return (self.value << pad).to_bytes((self.size + pad) // 8, "big")


def frame(payload: bytes) -> bytes:
    return RTCMMessage(payload=payload).serialize()


def msm(
    system: str,
    tow_ms: int,
    sats: Sequence[tuple[int, float, float]],
    msm7: bool,
    more: bool = False,
    station: int = 7,
) -> bytes:
    """One MSM4 or MSM7 frame: ``sats`` = (PRN, pseudorange m, C/N0 dB-Hz) on the system's signal."""
    bits = Bits()
    bits.put(MESSAGE_BASE[system] + (7 if msm7 else 4), 12)
    bits.put(station, 12)
    bits.put(tow_ms, 30)
    bits.put(1 if more else 0, 1)  # DF393 multiple message
    bits.put(0, 3)  # DF409 IODS
    bits.put(0, 7)  # reserved
    bits.put(0, 2)  # DF411
    bits.put(0, 2)  # DF412
    bits.put(0, 1)  # DF417
    bits.put(0, 3)  # DF418
    sats = sorted(sats)
    mask = 0
    for prn, _, _ in sats:
        mask |= 1 << (64 - prn)
    bits.put(mask, 64)
    bits.put(1 << (32 - SIGNAL_ID[system]), 32)
    bits.put((1 << len(sats)) - 1, len(sats))  # every satellite has the one signal
    fine_unit = 2.0**-29 if msm7 else 2.0**-24
    rough, fine = [], []
    for _, pseudorange, _ in sats:
        ms = pseudorange / MS_M
        whole = int(ms)
        fraction = round((ms - whole) * 1024) / 1024
        if fraction >= 1.0:
            whole, fraction = whole + 1, fraction - 1.0
        rough.append((whole, round(fraction * 1024)))
        fine.append(round((ms - whole - fraction) / fine_unit))
    for whole, _ in rough:
        bits.put(whole, 8)
    if msm7:
        for _ in sats:
            bits.put(0, 4)  # extended satellite info
    for _, fraction in rough:
        bits.put(fraction, 10)
    if msm7:
        for _ in sats:
            bits.put(0, 14)  # rough phase range rate
        for value in fine:
            bits.put(value, 20)  # DF405
        for _ in sats:
            bits.put(0, 24)  # DF406 phase
        for _ in sats:
            bits.put(0, 10)  # DF407 lock time
        for _ in sats:
            bits.put(0, 1)  # DF420
        for _, _, cn0 in sats:
            bits.put(round(cn0 * 16), 10)  # DF408
        for _ in sats:
            bits.put(0, 15)  # DF404 fine phase range rate
    else:
        for value in fine:
            bits.put(value, 15)  # DF400
        for _ in sats:
            bits.put(0, 22)  # DF401
        for _ in sats:
            bits.put(0, 4)  # DF402
        for _ in sats:
            bits.put(0, 1)  # DF420
        for _, _, cn0 in sats:
            bits.put(round(cn0), 6)  # DF403
    return frame(bits.payload())


def station_position(xyz: Sequence[float], station: int = 7, kind: int = 1005) -> bytes:
    """A 1005 (or 1006, antenna height 0) frame with the antenna reference point ``xyz`` (ECEF m)."""
    bits = Bits()
    bits.put(kind, 12)
    bits.put(station, 12)
    bits.put(0, 6)  # ITRF year
    bits.put(1, 1)  # GPS
    bits.put(0, 1)  # GLONASS
    bits.put(1, 1)  # Galileo
    bits.put(0, 1)  # reference station indicator
    bits.put(round(xyz[0] * 1e4), 38)
    bits.put(0, 1)  # single receiver oscillator
    bits.put(0, 1)  # reserved
    bits.put(round(xyz[1] * 1e4), 38)
    bits.put(0, 2)  # quarter cycle
    bits.put(round(xyz[2] * 1e4), 38)
    if kind == 1006:
        bits.put(0, 16)
    return frame(bits.payload())


def descriptor(station: int = 7) -> bytes:
    """A 1007 antenna descriptor with an empty description (skipped by the service)."""
    bits = Bits()
    bits.put(1007, 12)
    bits.put(station, 12)
    bits.put(0, 8)  # DF029: no characters
    bits.put(0, 8)  # DF031 antenna setup id
    return frame(bits.payload())


def legacy_gps_header(tow_ms: int, station: int = 7) -> bytes:
    """A 1001 (legacy GPS L1 observations) with no satellite: a type the service refuses."""
    bits = Bits()
    bits.put(1001, 12)
    bits.put(station, 12)
    bits.put(tow_ms, 30)
    bits.put(0, 1)  # DF005 synchronous
    bits.put(0, 5)  # DF006 satellites
    bits.put(0, 1)  # DF007 smoothing
    bits.put(0, 3)  # DF008 interval
    return frame(bits.payload())
