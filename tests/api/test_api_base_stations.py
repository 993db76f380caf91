"""The reference-station resource end to end on the real recording of tests/data/gnss-rover: register the
station MARE, upload its RINEX observations or RTCM frames of them, and run gnss_tight sessions with and
without its corrections; the served fixes must be what `edgepos eval gnss-rinex --base` computes."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
import rtcmwrite
from apihelp import ADMIN, assert_error, make_settings, open_session
from edgepos.api.app import create_app
from edgepos.api.base_stations import epoch_of
from edgepos.eval.gnss_rinex import _score, evaluate
from edgepos.gnss.differential import base_position, corrections_from_epochs
from edgepos.gnss.ephemerides import parse_ephemerides
from edgepos.gnss.geodesy import geodetic_to_ecef
from edgepos.gnss.rinex_obs import DEFAULT_CODES, read_epochs, read_header
from edgepos.gnss.spp import read_reference
from edgepos.gnss.timesys import SECONDS_PER_WEEK
from edgepos.pipelines.base import StaticEnvironment
from edgepos.pipelines.gnss_tight import GnssTightPipeline
from fastapi.testclient import TestClient
from gnsswire import DATA, NAV, OBS, QUICK, REFERENCE, assert_option_refused, epochs, nav_text

BASE = DATA / "base-0-5min.rnx"
TEXT = {**ADMIN, "Content-Type": "text/plain"}
BINARY = {**ADMIN, "Content-Type": "application/octet-stream"}
OPTIONS = {**QUICK, "use_doppler": False}
BATCH_EPOCHS = 5  # within the default CPU budget per batch with the integrity monitor (10 are not)
MARE = {
    "station_id": "MARE",
    "position_ecef": [4777633.8950, 203108.9850, 4206595.1490],  # the file header's marker
    "antenna_delta": {"up": 0.0770, "east": 0.0, "north": 0.0},
}


def _setup(client, station=MARE, observations=True):
    assert client.put("/v1/ephemerides", content=nav_text(), headers=TEXT).status_code == 200
    response = client.post("/v1/base-stations", json=station, headers=ADMIN)
    assert response.status_code == 201, response.text
    if observations:
        response = client.post(
            f"/v1/base-stations/{station['station_id']}/observations", content=BASE.read_bytes(), headers=TEXT
        )
        assert response.status_code == 200, response.text
        return response.json()
    return None


def _run(client, vehicle, options, count, per_batch=None):
    session_id, token = open_session(client, vehicle_id=vehicle, pipeline="gnss_tight", options=options)
    per_batch = per_batch or BATCH_EPOCHS
    fixes = []
    for seq, first in enumerate(range(0, count, per_batch), start=1):
        items = [m for _, epoch in epochs(count)[first : first + per_batch] for m in epoch]
        response = client.post(
            f"/v1/sessions/{session_id}/batches", json={"seq": seq, "measurements": items}, headers=token
        )
        assert response.status_code == 200, response.text
        fixes.extend(response.json()["fixes"])
    return fixes


def test_register_list_get_delete(client):
    assert_error(client.get("/v1/base-stations/MARE", headers=ADMIN), 404, "not_found")
    info = _setup(client)
    assert info["epochs_read"] == 300 and info["epochs_stored"] == 300 and info["window_epochs"] == 300
    assert info["corrections"] > 300 * 8
    assert info["last_epoch"]["gps_seconds"] - info["first_epoch"]["gps_seconds"] == pytest.approx(299.0)
    station = client.get("/v1/base-stations/MARE", headers=ADMIN).json()
    expected = base_position(read_header(str(BASE)))
    assert station["position_ecef"] == [float(v) for v in expected]  # marker + antenna delta, as the eval
    assert station["position_source"] == "registered"
    assert math.degrees(station["latitude"]) == pytest.approx(41.5, abs=0.1)
    assert station["newest_epoch"] == info["last_epoch"] and station["newest_epoch_satellites"] > 8
    assert client.post("/v1/base-stations", json=MARE, headers=ADMIN).status_code == 409
    geodetic = {
        "station_id": "geo",
        "position_geodetic": {"latitude": 0.7, "longitude": 0.04, "height": 80.0},
    }
    assert client.post("/v1/base-stations", json=geodetic, headers=ADMIN).status_code == 201
    listed = client.get("/v1/base-stations", headers=ADMIN).json()["stations"]
    assert [s["station_id"] for s in listed] == ["MARE", "geo"]
    lat, lon, height = listed[1]["latitude"], listed[1]["longitude"], listed[1]["height"]
    assert (lat, lon, height) == pytest.approx((0.7, 0.04, 80.0), abs=1e-9)
    assert listed[1]["newest_epoch"] is None
    assert client.delete("/v1/base-stations/MARE", headers=ADMIN).status_code == 204
    assert_error(client.delete("/v1/base-stations/MARE", headers=ADMIN), 404, "not_found")


@pytest.mark.parametrize(
    "body, field",
    [
        ({"station_id": "x", "position_ecef": [1.0, 2.0, 3.0]}, "position_ecef"),
        ({"station_id": "x", "position_ecef": [6.4e6, 0.0]}, "position_ecef"),
        (
            {"station_id": "x", "position_geodetic": {"latitude": 2.0, "longitude": 0.0, "height": 0.0}},
            "latitude",
        ),
        ({"station_id": "bad id", "position_ecef": MARE["position_ecef"]}, "station_id"),
        (
            {**MARE, "position_geodetic": {"latitude": 0.7, "longitude": 0.0, "height": 0.0}},
            "position_geodetic",
        ),
        ({**MARE, "galileo_group_delay": "icd"}, "galileo_group_delay"),
    ],
)
def test_bad_registrations_name_the_field(client, body, field):
    error = assert_error(client.post("/v1/base-stations", json=body, headers=ADMIN), 422, "invalid_request")
    assert any(field in problem["field"] for problem in error["problems"]), error
    assert client.get("/v1/base-stations", headers=ADMIN).json()["stations"] == []


def test_writes_need_the_admin_key(client):
    _, token = open_session(client)
    assert client.post("/v1/base-stations", json=MARE, headers=token).status_code == 403
    assert client.get("/v1/base-stations", headers=token).status_code == 200


def test_unknown_station_and_station_without_position(client):
    assert client.put("/v1/ephemerides", content=nav_text(), headers=TEXT).status_code == 200
    upload = client.post("/v1/base-stations/nope/observations", content=BASE.read_bytes(), headers=TEXT)
    assert_error(upload, 404, "not_found")
    response = client.post(
        "/v1/sessions",
        json={"vehicle_id": "v", "pipeline": "gnss_tight", "options": {**OPTIONS, "base_station": "nope"}},
        headers=ADMIN,
    )
    assert assert_error(response, 404, "not_found")["problems"][0]["field"] == "options.base_station"
    assert client.post("/v1/base-stations", json={"station_id": "blank"}, headers=ADMIN).status_code == 201
    upload = client.post("/v1/base-stations/blank/observations", content=BASE.read_bytes(), headers=TEXT)
    assert "has no position" in assert_error(upload, 422, "invalid_request")["message"]
    response = client.post(
        "/v1/sessions",
        json={"vehicle_id": "v", "pipeline": "gnss_tight", "options": {**OPTIONS, "base_station": "blank"}},
        headers=ADMIN,
    )
    assert "has no position" in assert_error(response, 422, "invalid_request")["message"]
    response = client.post(
        "/v1/sessions",
        json={"vehicle_id": "v", "pipeline": "gnss_tight", "options": {**OPTIONS, "base_station": "nearest"}},
        headers=ADMIN,
    )
    assert_error(response, 422, "invalid_request")
    assert client.get("/v1/base-stations/blank", headers=ADMIN).json()["newest_epoch"] is None


def test_a_malformed_observation_file_is_refused_naming_the_line(client):
    _setup(client, observations=False)
    lines = BASE.read_text().splitlines(keepends=True)
    end = next(k for k, line in enumerate(lines) if "END OF HEADER" in line)
    lines[end + 1] = "> 2020 11 29 xx\n"
    response = client.post("/v1/base-stations/MARE/observations", content="".join(lines), headers=TEXT)
    error = assert_error(response, 422, "invalid_request")
    assert error["problems"][0]["field"] == f"body.line[{end + 2}]", error
    assert client.get("/v1/base-stations/MARE", headers=ADMIN).json()["newest_epoch"] is None


def test_base_observations_need_ephemerides(client):
    assert client.post("/v1/base-stations", json=MARE, headers=ADMIN).status_code == 201
    response = client.post("/v1/base-stations/MARE/observations", content=BASE.read_bytes(), headers=TEXT)
    assert "no ephemerides" in assert_error(response, 422, "invalid_request")["message"]


COUNT = 60


def test_sessions_with_the_station_match_the_eval_with_base(client):
    """Per-measurement reports, and fixes identical to the pipeline with the eval's own correction table
    (built from the same file as `edgepos eval gnss-rinex --base` does); the error change equals the eval's."""
    _setup(client)
    plain = _run(client, "plain", OPTIONS, COUNT)
    corrected = _run(client, "based", {**OPTIONS, "base_station": "MARE"}, COUNT)
    nearest = _run(client, "nearest", {**OPTIONS, "base_station": "nearest"}, COUNT)
    assert all(use["correction_applied"] is None for fix in plain for use in fix["measurements"])
    applied = [use["correction_applied"] for fix in corrected for use in fix["measurements"]]
    assert all(isinstance(flag, bool) for flag in applied) and 0.6 < np.mean(applied) < 1.0
    reasons = {
        use["correction_reason"]
        for fix in corrected
        for use in fix["measurements"]
        if not use["correction_applied"]
    }
    assert reasons and all(r.startswith("no correction for this satellite") for r in reasons), reasons
    # 'nearest' needs a position: the first batch has none (no fix yet, no site origin), the next ones do
    first = {u["correction_reason"] for fix in nearest[:BATCH_EPOCHS] for u in fix["measurements"]}
    assert first == {
        "no base data: the session has no fix yet and the site no origin, so no station is nearest"
    }
    later = [u["correction_applied"] for fix in nearest[BATCH_EPOCHS:] for u in fix["measurements"]]
    assert later == [u["correction_applied"] for fix in corrected[BATCH_EPOCHS:] for u in fix["measurements"]]

    # the eval's table and the pipeline, as evaluate() runs them
    codes = {s: DEFAULT_CODES[s] for s in "GC"}
    ephemerides = parse_ephemerides(nav_text())
    station = base_position(read_header(str(BASE)))
    table = corrections_from_epochs(
        read_epochs(str(BASE), codes), station, ephemerides.orbits, ephemerides.atmosphere, codes
    )
    pipeline = GnssTightPipeline()
    state = pipeline.create(pipeline.resolve_options({**OPTIONS, "base_station": "MARE"}), None)
    environment = StaticEnvironment(navigation=ephemerides, differential=table)
    from edgepos.api.measurement_schemas import (
        PseudorangeMeasurement,  # the wire -> observation conversion of the API
    )

    expected = []
    for first in range(0, COUNT, BATCH_EPOCHS):
        items = [
            PseudorangeMeasurement(**m).to_observation()
            for _, epoch in epochs(COUNT)[first : first + BATCH_EPOCHS]
            for m in epoch
        ]
        fixes, state = pipeline.process(state, items, environment)
        expected.extend(fixes)
    assert [f["latitude"] for f in corrected] == [f.latitude for f in expected]
    assert [[u["correction_applied"] for u in f["measurements"]] for f in corrected] == [
        [u.correction_applied for u in f.measurements] for f in expected
    ]

    # the horizontal errors change as the eval's do, on the same epochs
    reference = read_reference(str(REFERENCE))
    times = [t for t, _ in epochs(COUNT)]

    def rms(fixes):
        ecef = [geodetic_to_ecef(f["latitude"], f["longitude"], f["height"]) for f in fixes]
        return _score(times, ecef, reference, len(times))["horizontal_rms_m"]

    without = evaluate(str(OBS), str(NAV), str(REFERENCE), "GC", OPTIONS, COUNT)
    with_base = evaluate(str(OBS), str(NAV), str(REFERENCE), "GC", OPTIONS, COUNT, base_path=str(BASE))
    assert rms(plain) == pytest.approx(without["horizontal_rms_m"], rel=1e-9)
    assert rms(corrected) == pytest.approx(with_base["horizontal_rms_m"], rel=1e-9)
    assert rms(corrected) < rms(plain)


@pytest.mark.parametrize("value", ["drop", 1, None])
def test_mixed_corrections_out_of_its_choices_is_422_naming_it(client, value):
    assert_option_refused(client, {"mixed_corrections": value}, "options.mixed_corrections")


def _rtcm_of(first, count, msm7=True):
    """Frames of the base file's epochs first .. first+count-1: one MSM per system and epoch."""
    out = b""
    for number, epoch in enumerate(read_epochs(str(BASE))):
        if number < first:
            continue
        if number >= first + count:
            break
        tow = epoch.gpst % SECONDS_PER_WEEK
        for system in "GEC":
            rows = [
                (int(p), float(pr), float(c) if math.isfinite(c) else 0.0)
                for s, p, pr, c in zip(epoch.systems, epoch.prns, epoch.pseudorange_m, epoch.cn0_dbhz)
                if s == system and math.isfinite(pr)
            ]
            ms = round((tow - (14.0 if system == "C" else 0.0)) * 1000.0)  # BeiDou time is 14 s behind
            out += rtcmwrite.msm(system, ms, rows, msm7, more=system != "C")
    return out


def test_rtcm_sets_the_position_and_gives_the_rinex_corrections(client):
    _setup(client, {"station_id": "rt"}, observations=False)
    marker = MARE["position_ecef"]
    arp = [float(v) for v in base_position(read_header(str(BASE)))]
    frames = rtcmwrite.station_position(arp) + _rtcm_of(0, 20, msm7=True) + _rtcm_of(20, 10, msm7=False)
    response = client.post("/v1/base-stations/rt/rtcm", content=frames, headers=BINARY)
    assert response.status_code == 200, response.text
    info = response.json()
    assert info["position_set"] and info["epochs_stored"] == 30
    assert info["messages"] == {
        "1005": 1,
        "1077": 20,
        "1097": 20,
        "1127": 20,
        "1074": 10,
        "1094": 10,
        "1124": 10,
    }
    station = client.get("/v1/base-stations/rt", headers=ADMIN).json()
    assert (
        station["position_ecef"] == pytest.approx(arp, abs=1e-4) and station["position_source"] == "rtcm 1005"
    )
    assert station["position_ecef"] != marker
    # the same corrections as from the RINEX file, to the MSM resolution (MSM4: 2^-24 ms = 1.8 cm)
    assert client.post("/v1/base-stations", json=MARE, headers=ADMIN).status_code == 201
    assert (
        client.post(
            "/v1/base-stations/MARE/observations", content=BASE.read_bytes(), headers=TEXT
        ).status_code
        == 200
    )
    store = client.app.state.context.store
    import asyncio

    from edgepos.api.base_stations import epoch_of

    rtcm = asyncio.run(store.base_window("rt", 0.0, 2e9)).epochs
    rinex = {t: epoch_of(d) for t, d in asyncio.run(store.base_window("MARE", 0.0, 2e9)).epochs}
    assert len(rtcm) == 30
    for t, document in rtcm:
        ours, theirs = epoch_of(document), rinex[t]
        assert ours.sats == theirs.sats and ours.issues == theirs.issues
        assert np.max(np.abs(ours.correction_m - theirs.correction_m)) < 0.02


def test_stale_and_missing_corrections_are_reported_per_measurement(client):
    _setup(client, {"station_id": "rt", "position_ecef": MARE["position_ecef"]}, observations=False)
    response = client.post("/v1/base-stations/rt/rtcm", content=_rtcm_of(0, 5), headers=BINARY)
    assert response.status_code == 200, response.text
    fixes = _run(
        client, "stale", {**OPTIONS, "base_station": "rt", "max_correction_age_s": 3.0}, 12, per_batch=4
    )
    for number, fix in enumerate(fixes):
        pseudoranges = [u for u in fix["measurements"] if u["type"] == "pseudorange"]
        if number <= 4 + 3:  # base epochs 0-4, held for at most 3 s
            assert any(u["correction_applied"] for u in pseudoranges)
        else:
            assert not any(u["correction_applied"] for u in pseudoranges)
            reasons = {u["correction_reason"].split(":")[0] for u in pseudoranges}
            assert "correction too old" in reasons, reasons
            assert reasons <= {"correction too old", "no correction for this satellite", "no base data"}
    # the station deleted: a session naming it goes on, and each pseudorange says why it has no correction
    session_id, token = open_session(
        client, vehicle_id="orphan", pipeline="gnss_tight", options={**OPTIONS, "base_station": "rt"}
    )
    assert client.delete("/v1/base-stations/rt", headers=ADMIN).status_code == 204
    items = [m for _, epoch in epochs(12)[:2] for m in epoch]
    response = client.post(
        f"/v1/sessions/{session_id}/batches", json={"seq": 1, "measurements": items}, headers=token
    )
    assert response.status_code == 200, response.text
    reasons = {u["correction_reason"] for fix in response.json()["fixes"] for u in fix["measurements"]}
    assert reasons == {"no base data: base station 'rt' is not registered (deleted?)"}


def test_bad_rtcm_is_refused_naming_the_message_and_nothing_changes(client):
    _setup(client, {"station_id": "rt"}, observations=False)
    good = rtcmwrite.station_position(MARE["position_ecef"]) + _rtcm_of(0, 2)
    first_len = len(rtcmwrite.station_position(MARE["position_ecef"]))
    broken = bytearray(good)
    broken[first_len + 10] ^= 0xFF  # inside the second frame (the first epoch's GPS MSM7): CRC fails
    response = client.post("/v1/base-stations/rt/rtcm", content=bytes(broken), headers=BINARY)
    error = assert_error(response, 422, "invalid_request")
    assert "frame 2 (message 1077" in error["message"], error
    assert error["problems"][0]["field"].startswith("body.frame 2")
    station = client.get("/v1/base-stations/rt", headers=ADMIN).json()
    assert station["position_ecef"] is None and station["newest_epoch"] is None
    for body, words in ((good[:-5], "ends inside the frame"), (b"\x00" + good, "preamble"), (b"", "no GPS")):
        response = client.post("/v1/base-stations/rt/rtcm", content=body, headers=BINARY)
        assert words in assert_error(response, 422, "invalid_request")["message"]


def test_descriptors_are_skipped_and_legacy_observations_refused(client):
    _setup(client, {"station_id": "rt", "position_ecef": MARE["position_ecef"]}, observations=False)
    frames = rtcmwrite.descriptor() + _rtcm_of(0, 1)
    response = client.post("/v1/base-stations/rt/rtcm", content=frames, headers=BINARY)
    assert response.status_code == 200, response.text
    assert response.json()["messages"] == {"1007": 1, "1077": 1, "1097": 1, "1127": 1}
    legacy = _rtcm_of(1, 1) + rtcmwrite.legacy_gps_header(0)
    error = assert_error(
        client.post("/v1/base-stations/rt/rtcm", content=legacy, headers=BINARY), 422, "invalid_request"
    )
    assert "frame 4 (message 1001" in error["message"] and "not accepted" in error["message"], error
    assert (
        client.get("/v1/base-stations/rt", headers=ADMIN).json()["newest_epoch"]["gps_seconds"]
        == epochs(1)[0][0]
    )


def test_an_ephemeris_issue_the_base_did_not_use_gets_no_correction(client):
    """Corrections computed with one ephemeris of G05, then a navigation file whose G05 records carry another
    IODE: the rover's G05 is told the issues differ, the other satellites are still corrected."""
    _setup(client)
    lines = nav_text().splitlines(keepends=True)
    for k, line in enumerate(lines):
        if line.startswith("G05 "):
            iode = float(lines[k + 1][4:23].replace("D", "E"))
            lines[k + 1] = f"    {iode + 100:19.12e}{lines[k + 1][23:]}"
    assert client.put("/v1/ephemerides", content="".join(lines), headers=TEXT).status_code == 200
    (fix,) = _run(client, "issue", {**OPTIONS, "base_station": "MARE"}, 1)
    sent = epochs(1)[0][1]
    by_sat = {f"{sent[u['index']]['system']}{sent[u['index']]['prn']:02d}": u for u in fix["measurements"]}
    assert by_sat["G05"]["correction_applied"] is False
    assert by_sat["G05"]["correction_reason"].startswith("ephemeris issue mismatch: base IODE 39 ")
    assert "rover IODE 139 " in by_sat["G05"]["correction_reason"]
    assert sum(u["correction_applied"] for u in by_sat.values()) >= 10


def test_old_uploads_are_refused(client):
    _setup(client, observations=False)
    lines = BASE.read_text().splitlines(keepends=True)
    end = next(k for k, line in enumerate(lines) if "END OF HEADER" in line)
    header, body = lines[: end + 1], lines[end + 1 :]
    assert (
        client.post("/v1/base-stations/MARE/observations", content="".join(lines), headers=TEXT).status_code
        == 200
    )
    # the same file an hour earlier (12:40 -> 11:40): older than any session may use
    shifted = [f"{line[:13]}11{line[15:]}" if line.startswith(">") else line for line in body]
    assert shifted[0].startswith("> 2020 11 29 11 40 00")
    response = client.post(
        "/v1/base-stations/MARE/observations", content="".join(header + shifted), headers=TEXT
    )
    assert "older than the station's newest" in assert_error(response, 422, "invalid_request")["message"]


def test_upload_size_limit(tmp_path):
    settings = make_settings(tmp_path, max_base_observations_bytes=4096)
    with TestClient(create_app(settings)) as small:
        _setup(small, observations=False)
        response = small.post("/v1/base-stations/MARE/observations", content=BASE.read_bytes(), headers=TEXT)
        assert (
            "EDGEPOS_MAX_BASE_OBSERVATIONS_BYTES"
            in assert_error(response, 413, "payload_too_large")["message"]
        )


def test_two_workers_share_the_station_through_the_store(tmp_path):
    """Registered and fed on one worker, used by a session on another (a SQLite store both open)."""
    url = f"sqlite:///{tmp_path / 'store.db'}"
    with (
        TestClient(create_app(make_settings(tmp_path, store=url))) as a,
        TestClient(create_app(make_settings(tmp_path, store=url))) as b,
    ):
        _setup(a, {"station_id": "rt", "position_ecef": MARE["position_ecef"]}, observations=False)
        assert a.post("/v1/base-stations/rt/rtcm", content=_rtcm_of(0, 3), headers=BINARY).status_code == 200
        assert b.get("/v1/base-stations/rt", headers=ADMIN).json()["newest_epoch_satellites"] > 8
        fixes = _run(b, "elsewhere", {**OPTIONS, "base_station": "rt"}, 3, per_batch=3)
        assert all(any(u["correction_applied"] for u in fix["measurements"]) for fix in fixes)


def test_a_stations_galileo_group_delay_moves_its_galileo_corrections_only(client):
    """Registered with galileo_group_delay none, the station's Galileo corrections differ from broadcast's by
    each satellite's BGD (the record's own clock pair's), its GPS and BeiDou ones not at all; the setting is
    shown, kept through the store and by default broadcast."""
    _setup(client)
    assert client.get("/v1/base-stations/MARE", headers=ADMIN).json()["galileo_group_delay"] == "broadcast"
    plain = {**MARE, "station_id": "MARE-none", "galileo_group_delay": "none"}
    response = client.post("/v1/base-stations", json=plain, headers=ADMIN)
    assert response.status_code == 201 and response.json()["galileo_group_delay"] == "none"
    response = client.post(
        "/v1/base-stations/MARE-none/observations", content=BASE.read_bytes(), headers=TEXT
    )
    assert response.status_code == 200, response.text
    listed = {s["station_id"]: s for s in client.get("/v1/base-stations", headers=ADMIN).json()["stations"]}
    assert listed["MARE-none"]["galileo_group_delay"] == "none"
    store = client.app.state.context.store
    windows = [asyncio.run(store.base_window(s, 0.0, 2e9)).epochs for s in ("MARE", "MARE-none")]
    broadcast, none = (epoch_of(window[-1][1]) for window in windows)
    assert broadcast.sats == none.sats and broadcast.gpst == none.gpst
    by_sat = dict(zip(broadcast.sats, none.correction_m - broadcast.correction_m, strict=True))
    assert all(abs(v) < 1e-9 for sat, v in by_sat.items() if sat[0] != "E")
    galileo = {sat: v for sat, v in by_sat.items() if sat[0] == "E"}
    assert len(galileo) >= 4 and max(abs(v) for v in galileo.values()) > 1.0
