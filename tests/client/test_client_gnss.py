"""The clients' GNSS calls: ephemerides up, down and gone, and pseudorange / riss models, against the real app
in-process (async) and a real server process over a socket (sync), on the real receiver recording."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import pytest
from clienthelp import ADMIN_KEY
from edgepos_client import (
    AsyncEdgeposClient,
    EdgeposClient,
    InvalidRequest,
    NotFound,
    PseudorangeMeasurement,
    RissMeasurement,
)
from pydantic import ValidationError

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "api"))
from gnsswire import NAV, QUICK, horizontal_error, measurements, nav_text, with_carrier, with_doppler


def pseudoranges(first: int, count: int) -> list[PseudorangeMeasurement]:
    items = measurements(first, count)
    return [PseudorangeMeasurement(**{k: v for k, v in m.items() if k != "type"}) for m in items]


@pytest.mark.anyio
async def test_async_client_ephemerides_and_pseudoranges(aclient: AsyncEdgeposClient) -> None:
    with pytest.raises(NotFound):
        await aclient.get_ephemerides()
    loaded = await aclient.put_ephemerides(NAV)  # a path is read and sent as text/plain
    assert loaded.systems == ["C", "E", "G"] and loaded.satellite_count == 45 and loaded.klobuchar
    assert loaded.valid_from is not None and loaded.valid_from.week == 2134
    again = await aclient.put_ephemerides(nav_text())  # text: the same file
    assert again.digest == loaded.digest and again.uploaded_at >= loaded.uploaded_at
    session = await aclient.create_session("gnss-car", "gnss_tight", options=QUICK)
    assert await aclient.get_ephemerides(session) == again
    t0 = measurements(0, 1)[0]["t"]
    riss = RissMeasurement(t=t0, wheel_speed=0.0, accel_x=0.0, accel_y=0.0, gyro_z=0.0)
    fixes = await aclient.send_batch(session, [riss, *pseudoranges(0, 1)])
    fixes += await aclient.send_batch(session, pseudoranges(1, 2))
    assert [fix.status for fix in fixes] == ["initialised", "tracking", "tracking"]
    assert all(fix.height is not None and fix.latitude is not None for fix in fixes)
    assert fixes[0].measurements[0].type == "riss" and fixes[0].measurements[0].used
    with pytest.raises(InvalidRequest) as caught:
        await aclient.send_batch(session, [{**measurements(3, 1)[0], "prn": 60, "system": "C"}])
    assert caught.value.problems[0].field == "measurements[0].prn"
    with pytest.raises(InvalidRequest) as caught:
        await aclient.put_ephemerides("not a navigation file\n")
    assert caught.value.problems[0].field == "body.line[1]"
    await aclient.delete_ephemerides()
    with pytest.raises(NotFound):
        await aclient.delete_ephemerides()


@pytest.mark.anyio
async def test_the_client_sends_dopplers_and_reads_what_became_of_them(aclient: AsyncEdgeposClient) -> None:
    await aclient.put_ephemerides(NAV)
    session = await aclient.create_session("doppler-car", "gnss_tight", options=QUICK)
    batch = [
        PseudorangeMeasurement(**{k: v for k, v in m.items() if k != "type"})
        for m in with_doppler(measurements(0, 3))
    ]
    assert sum(m.doppler_hz is not None for m in batch) > 10
    fixes = await aclient.send_batch(session, batch)
    reports = {
        use.index: use for fix in fixes for use in fix.measurements
    }  # each measurement in its epoch's fix
    assert sorted(reports) == list(range(len(batch)))
    for index, sent in enumerate(batch):  # a Doppler sent is reported used or why not; none sent, null
        assert (reports[index].doppler_used is None) == (sent.doppler_hz is None)
    assert any(use.doppler_used for use in reports.values())
    assert all(use.doppler_reason for use in reports.values() if use.doppler_used is False)
    await aclient.delete_ephemerides()


@pytest.mark.anyio
async def test_the_client_sends_carrier_phase(aclient: AsyncEdgeposClient) -> None:
    """Carrier phase and LLI from the recording go out with the pseudoranges and are accepted; the session
    smooths with them (its fixes differ from code alone)."""
    await aclient.put_ephemerides(NAV)
    latitudes = {}
    for carrier in (True, False):
        session = await aclient.create_session(f"carrier-car-{carrier}", "gnss_tight", options=QUICK)
        fixes = []
        phases = 0
        for epoch in range(4):
            items = with_doppler(measurements(epoch, 1))
            batch = [
                PseudorangeMeasurement(**{k: v for k, v in m.items() if k != "type"})
                for m in (with_carrier(items) if carrier else items)
            ]
            phases += sum(m.carrier_cycles is not None and m.lli is not None for m in batch)
            fixes += await aclient.send_batch(session, batch)
        assert (phases > 10) == carrier
        latitudes[carrier] = [fix.latitude for fix in fixes]
    assert latitudes[True] != latitudes[False]
    await aclient.delete_ephemerides()


def test_models_check_before_sending() -> None:
    item = measurements(0, 1)[0]
    with pytest.raises(ValidationError):
        PseudorangeMeasurement(**{**item, "type": "pseudorange", "system": "R"})
    with pytest.raises(ValidationError):
        PseudorangeMeasurement(**{**item, "type": "pseudorange", "pseudorange_m": math.nan})
    for doppler in (20000.5, math.inf, math.nan):
        with pytest.raises(ValidationError):
            PseudorangeMeasurement(**{**item, "type": "pseudorange", "doppler_hz": doppler})
    for change in ({"carrier_cycles": 1.0e10}, {"carrier_cycles": math.nan}, {"lli": 8}, {"lli": -1}):
        with pytest.raises(ValidationError):
            PseudorangeMeasurement(**{**item, "type": "pseudorange", **change})
    with pytest.raises(ValidationError):
        RissMeasurement(t=-1.0, wheel_speed=0.0, accel_x=0.0, accel_y=0.0, gyro_z=0.0)


@pytest.mark.slow
def test_sync_client_over_a_socket(server_url: str) -> None:
    with EdgeposClient(server_url, ADMIN_KEY, timeout=30.0) as client:
        loaded = client.put_ephemerides(nav_text().encode())
        assert client.get_ephemerides().digest == loaded.digest
        session = client.create_session("gnss-socket-car", "gnss_tight", options=QUICK)
        fixes = [fix for first in (0, 5) for fix in client.send_batch(session, pseudoranges(first, 5))]
        assert len(fixes) == 10 and session.last_seq == 2
        errors = [e for e in (horizontal_error(fix.model_dump()) for fix in fixes) if e is not None]
        assert len(errors) >= 8 and max(errors) < 10.0, errors
        client.delete_ephemerides()
        with pytest.raises(NotFound):
            client.get_ephemerides()
