"""GNSS time scales: calendar <-> continuous GPS seconds, GPS week/seconds of week, BeiDou time.

Every time in the package is continuous GPS time in seconds since the GPS epoch 1980-01-06 00:00:00
(``gpst``). float64 holds it to about 0.2 microseconds, i.e. well below a millimetre of satellite motion.
"""

from __future__ import annotations

import datetime as _dt

SECONDS_PER_WEEK = 604800.0
GPS_EPOCH = _dt.datetime(1980, 1, 6)
BDT_MINUS_GPST_S = -14.0
"""BeiDou time lags GPS time by 14 s (BDT = GPST - 14 s)."""
BDT_WEEK_OFFSET = 1356
"""BDT week 0 started at GPS week 1356 (2006-01-01 00:00:00 UTC)."""


def calendar_to_seconds(year: int, month: int, day: int, hour: int, minute: int, second: float) -> float:
    """Calendar date in some GNSS time scale -> seconds since 1980-01-06 00:00:00 of that same scale."""
    days = (_dt.date(year, month, day) - GPS_EPOCH.date()).days
    return days * 86400.0 + hour * 3600.0 + minute * 60.0 + second


def week_seconds(gpst: float) -> tuple[int, float]:
    """Continuous GPS seconds -> (GPS week, seconds of week)."""
    week = int(gpst // SECONDS_PER_WEEK)
    return week, gpst - week * SECONDS_PER_WEEK


def from_week_seconds(week: int, sow: float) -> float:
    """(GPS week, seconds of week) -> continuous GPS seconds."""
    return week * SECONDS_PER_WEEK + sow


def bdt_to_gpst(bdt_since_gps_epoch: float) -> float:
    """A BeiDou-time instant counted from 1980-01-06 (as read from a BDT calendar) -> GPST seconds."""
    return bdt_since_gps_epoch - BDT_MINUS_GPST_S


def bdt_week_to_gpst(bdt_week: int, bdt_sow: float) -> float:
    """(BDT week, BDT seconds of week) -> continuous GPS seconds."""
    return (bdt_week + BDT_WEEK_OFFSET) * SECONDS_PER_WEEK + bdt_sow - BDT_MINUS_GPST_S
