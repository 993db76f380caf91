"""The real receiver recording of tests/data/gnss-rover on the wire: the navigation file, the first epochs
of GPS + BeiDou pseudoranges as ``pseudorange`` measurements, and the reference trajectory."""

from __future__ import annotations

import functools
import math
from pathlib import Path
from typing import Any

import numpy as np
from apihelp import ADMIN, assert_error, open_session
from edgepos.gnss.geodesy import ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs
from edgepos.gnss.spp import read_reference
from edgepos.gnss.timesys import SECONDS_PER_WEEK

DATA = Path(__file__).resolve().parents[1] / "data" / "gnss-rover"
NAV = DATA / "broadcast-nav.rnx"
OBS = DATA / "rover-0-5min.rnx"
REFERENCE = DATA / "reference-0-5min.csv"
QUICK = {"filter": "ukf", "seed": 1, "systems": ["G", "C"]}
"""Session options that keep a test about the API fast (a single UKF)."""


@functools.lru_cache(maxsize=1)
def nav_text() -> str:
    return NAV.read_text(encoding="ascii")


def upload_ephemerides(client: Any) -> None:
    """PUT the recording's navigation file as the site's ephemerides (admin)."""
    upload = client.put(
        "/v1/ephemerides", content=nav_text(), headers={"Content-Type": "text/plain", **ADMIN}
    )
    assert upload.status_code == 200, upload.text


def quick_fixes(client: Any, vehicle: str, options: dict[str, Any]) -> list[dict[str, Any]]:
    """The fixes of a new gnss_tight session for ``vehicle`` fed the recording's first ten epochs in three
    batches (each within the session's CPU budget)."""
    session_id, token = open_session(client, pipeline="gnss_tight", vehicle_id=vehicle, options=options)
    fixes: list[dict[str, Any]] = []
    for seq, first in enumerate((0, 4, 8), start=1):
        body = {"seq": seq, "measurements": measurements(first, min(4, 10 - first))}
        response = client.post(f"/v1/sessions/{session_id}/batches", json=body, headers=token)
        assert response.status_code == 200, response.text
        fixes += response.json()["fixes"]
    return fixes


def assert_option_refused(client: Any, options: dict[str, Any], field: str) -> None:
    """Opening a quick gnss_tight session with ``options`` is a 422 whose problems name ``field``."""
    response = client.post(
        "/v1/sessions",
        json={"vehicle_id": "car-9", "pipeline": "gnss_tight", "options": {**QUICK, **options}},
        headers=ADMIN,
    )
    error = assert_error(response, 422, "invalid_request")
    assert field in {p["field"] for p in error["problems"]}, error


@functools.lru_cache(maxsize=2)
def epochs(count: int = 10) -> tuple[tuple[float, tuple[dict[str, Any], ...]], ...]:
    """The first ``count`` epochs: (GPS seconds, pseudorange measurements of GPS and BeiDou)."""
    codes = {system: DEFAULT_CODES[system] for system in ("G", "C")}
    out = []
    for number, epoch in enumerate(read_epochs(str(OBS), codes)):
        if number >= count:
            break
        tow = epoch.gpst % SECONDS_PER_WEEK
        measurements = tuple(
            {
                "type": "pseudorange",
                "t": tow,
                "system": system,
                "prn": int(prn),
                "pseudorange_m": float(pr),
                "cn0_dbhz": float(cn0) if math.isfinite(cn0) else 0.0,
            }
            for system, prn, pr, cn0 in zip(epoch.systems, epoch.prns, epoch.pseudorange_m, epoch.cn0_dbhz)
            if math.isfinite(pr) and 1.0e6 <= pr <= 1.0e8
        )
        out.append((float(epoch.gpst), measurements))
    return tuple(out)


@functools.lru_cache(maxsize=1)
def _dopplers() -> dict[tuple[float, str, int], float]:
    """(time of week, system, PRN) -> the recording's Doppler (Hz) of the pseudorange's own signal."""
    codes = {system: DEFAULT_CODES[system] for system in ("G", "C")}
    out = {}
    for number, epoch in enumerate(read_epochs(str(OBS), codes)):
        if number >= 10:
            break
        for system, prn, doppler in zip(epoch.systems, epoch.prns, epoch.doppler_hz):
            if math.isfinite(doppler):
                out[(epoch.gpst % SECONDS_PER_WEEK, system, int(prn))] = float(doppler)
    return out


def with_doppler(items: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The pseudorange measurements with their Doppler (doppler_hz) from the recording, where it has one."""
    dopplers = _dopplers()
    out = []
    for m in items:
        doppler = dopplers.get((m["t"], m["system"], m["prn"]))
        out.append(m if doppler is None else {**m, "doppler_hz": doppler})
    return out


@functools.lru_cache(maxsize=1)
def _carriers() -> dict[tuple[float, str, int], tuple[float, int]]:
    """(time of week, system, PRN) -> the recording's carrier phase (cycles) and LLI of the pseudorange's signal."""
    codes = {system: DEFAULT_CODES[system] for system in ("G", "C")}
    out = {}
    for number, epoch in enumerate(read_epochs(str(OBS), codes)):
        if number >= 10:
            break
        for system, prn, cycles, lli in zip(epoch.systems, epoch.prns, epoch.carrier_cycles, epoch.lli):
            if math.isfinite(cycles):
                out[(epoch.gpst % SECONDS_PER_WEEK, system, int(prn))] = (float(cycles), int(lli))
    return out


def with_carrier(items: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The pseudorange measurements with their carrier phase and LLI from the recording, where it has one."""
    carriers = _carriers()
    out = []
    for m in items:
        found = carriers.get((m["t"], m["system"], m["prn"]))
        out.append(m if found is None else {**m, "carrier_cycles": found[0], "lli": found[1]})
    return out


def measurements(first: int, count: int, satellites: set[str] | None = None) -> list[dict[str, Any]]:
    """Pseudoranges of epochs first .. first+count-1, only of ``satellites`` (e.g. 'G05') when given."""
    return [
        m
        for _, epoch in epochs()[first : first + count]
        for m in epoch
        if satellites is None or f"{m['system']}{m['prn']:02d}" in satellites
    ]


def horizontal_error(fix: dict[str, Any]) -> float | None:
    """Horizontal distance (m) between a wire fix's latitude/longitude/height and the reference at its t;
    None where the reference has a gap."""
    ref_time, ref_ecef = read_reference(str(REFERENCE))
    tow = np.mod(ref_time, SECONDS_PER_WEEK)
    row = int(np.argmin(np.abs(tow - fix["t"])))
    if abs(tow[row] - fix["t"]) > 0.05:
        return None
    truth = ref_ecef[row]
    position = geodetic_to_ecef(fix["latitude"], fix["longitude"], fix["height"])
    lat, lon, _ = ecef_to_geodetic(truth)
    east, north, _ = enu_rotation(float(lat), float(lon)) @ (np.asarray(position) - truth)
    return math.hypot(float(east), float(north))
