"""GNSS on the wire: PUT/GET/DELETE /v1/ephemerides, pseudorange and riss measurements, and gnss_tight fixes
with latitude, longitude and height, end to end on the real receiver recording of tests/data/gnss-rover."""

from __future__ import annotations

import hashlib
import math

import numpy as np
import pytest
from apihelp import ADMIN, NO_DOPPLER, assert_error, make_settings, open_session
from edgepos.api.app import create_app
from edgepos.core.observations import PseudorangeObservation
from edgepos.gnss.ephemerides import DEFAULT_SIGNAL, parse_ephemerides
from edgepos.gnss.orbits import group_delay_factors
from edgepos.pipelines import cost
from edgepos.pipelines.registry import get_pipeline
from fastapi.testclient import TestClient
from gnsswire import QUICK, epochs, horizontal_error, measurements, nav_text, with_carrier, with_doppler

TEXT = {"Content-Type": "text/plain"}


def upload(client, text: str | bytes | None = None, headers=ADMIN):
    body = nav_text() if text is None else text
    return client.put("/v1/ephemerides", content=body, headers={**TEXT, **headers})


def post(client, session_id, token, seq, items, **extra):
    return client.post(
        f"/v1/sessions/{session_id}/batches", json={"seq": seq, "measurements": items, **extra}, headers=token
    )


def _with_satellite_states(items: list[dict], rates: bool = False) -> tuple[list[dict], float]:
    """The first epoch's measurements with the satellite positions and clocks a client would compute from
    the same broadcast ephemerides (sat_position, sat_clock; with ``rates`` also sat_velocity and
    sat_clock_drift), and the epoch's GPS time."""
    ephemerides = parse_ephemerides(nav_text())
    gpst = epochs()[0][0]
    systems = [m["system"] for m in items]
    index = ephemerides.orbits.select(systems, [m["prn"] for m in items], gpst)
    factors = np.array([group_delay_factors(s, DEFAULT_SIGNAL[s]) for s in systems])
    states = ephemerides.orbits.transmit_states(index, gpst, [m["pseudorange_m"] for m in items], factors)
    sent = [
        {**m, "sat_position": [float(v) for v in states.position[k]], "sat_clock": float(states.clock_s[k])}
        for k, m in enumerate(items)
    ]
    if rates:
        sent = [
            {
                **m,
                "sat_velocity": [float(v) for v in states.velocity[k]],
                "sat_clock_drift": float(states.clock_drift[k]),
            }
            for k, m in enumerate(sent)
        ]
    return sent, gpst


def test_ephemerides_put_get_delete(client):
    assert_error(client.get("/v1/ephemerides", headers=ADMIN), 404, "not_found")
    response = upload(client)
    assert response.status_code == 200, response.text
    summary = response.json()
    assert summary["digest"] == hashlib.sha256(nav_text().encode()).hexdigest()
    assert summary["size_bytes"] == len(nav_text().encode())
    assert summary["systems"] == ["C", "E", "G"]
    assert summary["satellite_count"] == len(summary["satellites"]) == 45
    assert {"G05", "C07", "E01"} <= set(summary["satellites"])
    assert summary["records"] == {"C": 23, "E": 82, "G": 24}
    assert summary["skipped_records"] == {"R": 44, "S": 71}
    assert summary["klobuchar"] is True and {"GPSA", "GPSB"} <= set(summary["ionosphere"])
    start, end = summary["valid_from"], summary["valid_until"]
    assert start["week"] == 2134 and end["gps_seconds"] > start["gps_seconds"]
    assert start["gps_seconds"] == start["week"] * 604800 + start["tow"]
    # The recording (2020-11-29 12:40 GPST, week 2134 second 45600) lies inside the window.
    assert start["gps_seconds"] < 2134 * 604800 + 45600 < end["gps_seconds"]

    _session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    assert client.get("/v1/ephemerides", headers=token).json() == summary  # any session token reads
    assert_error(upload(client, headers=token), 403, "forbidden")
    assert_error(client.delete("/v1/ephemerides", headers=token), 403, "forbidden")
    assert_error(client.get("/v1/ephemerides"), 401, "unauthorized")
    assert_error(upload(client, headers={}), 401, "unauthorized")

    assert client.delete("/v1/ephemerides", headers=ADMIN).status_code == 204
    assert_error(client.get("/v1/ephemerides", headers=ADMIN), 404, "not_found")
    assert_error(client.delete("/v1/ephemerides", headers=ADMIN), 404, "not_found")


def test_octet_stream_upload_and_replacement(client):
    first = client.put(
        "/v1/ephemerides",
        content=nav_text().encode(),
        headers={**ADMIN, "Content-Type": "application/octet-stream"},
    )
    assert first.status_code == 200, first.text
    # Only GPS records: a new file replaces the old one whole.
    lines = nav_text().splitlines(keepends=True)
    header_end = next(i for i, line in enumerate(lines) if "END OF HEADER" in line) + 1
    body = lines[:header_end]
    i = header_end
    while i < len(lines):
        if lines[i][0] == "G":
            body.extend(lines[i : i + 8])
            i += 8
        else:
            i += 1
    second = upload(client, "".join(body))
    assert second.status_code == 200, second.text
    assert second.json()["systems"] == ["G"] and second.json()["digest"] != first.json()["digest"]
    assert client.get("/v1/ephemerides", headers=ADMIN).json() == second.json()


@pytest.mark.parametrize(
    ("edit", "line", "words"),
    [
        (lambda ls: ls.__setitem__(0, ls[0].replace("3.04", "2.11")), 1, "version"),
        (
            lambda ls: ls.__setitem__(12, ls[12][:4] + "   x.50000000D+00" + ls[12][19:]),
            13,
            "cannot read number",
        ),
        (lambda ls: ls.__delitem__(slice(12, 13)), None, "expected"),
    ],
)
def test_a_malformed_file_is_refused_naming_the_line(client, edit, line, words):
    assert upload(client).status_code == 200
    loaded = client.get("/v1/ephemerides", headers=ADMIN).json()
    lines = nav_text().splitlines(keepends=True)
    header_end = next(i for i, text in enumerate(lines) if "END OF HEADER" in text) + 1
    assert header_end == 11  # the edits above address the first record (lines 12-19)
    edit(lines)
    error = assert_error(upload(client, "".join(lines)), 422, "invalid_request")
    (problem,) = error["problems"]
    assert words in problem["reason"]
    if line is not None:
        assert problem["field"] == f"body.line[{line}]" and f"line {line}" in error["message"]
    else:
        assert problem["field"].startswith("body.line[")
    assert client.get("/v1/ephemerides", headers=ADMIN).json() == loaded  # the loaded file stays


def test_a_byte_order_mark_and_crlf_line_ends_are_accepted(client):
    windows = "\ufeff" + nav_text().replace("\n", "\r\n")
    response = upload(client, windows.encode("utf-8"))
    assert response.status_code == 200, response.text
    assert response.json()["satellite_count"] == 45


def test_not_text_and_no_usable_record_are_refused(client):
    error = assert_error(upload(client, b"\xff\xfe binary"), 422, "invalid_request")
    assert error["problems"][0]["field"] == "body.line[1]" and "not text" in error["problems"][0]["reason"]
    header = "".join(nav_text().splitlines(keepends=True)[:11])
    error = assert_error(upload(client, header), 422, "invalid_request")
    assert "no healthy GPS, BeiDou or Galileo ephemeris" in error["problems"][0]["reason"]
    assert_error(client.get("/v1/ephemerides", headers=ADMIN), 404, "not_found")


def test_size_limit_is_its_own_and_checked_before_parsing(tmp_path):
    size = len(nav_text().encode())
    small = make_settings(tmp_path, max_body_bytes=4096, max_ephemerides_bytes=size - 1)
    with TestClient(create_app(small)) as client:
        error = assert_error(upload(client), 413, "payload_too_large")
        assert "EDGEPOS_MAX_EPHEMERIDES_BYTES" in error["message"]
        # Not parsed: garbage of the same size gets the same 413, not a 422.
        assert_error(upload(client, "x" * size), 413, "payload_too_large")
    roomy = make_settings(tmp_path, max_body_bytes=4096, max_ephemerides_bytes=size)
    with TestClient(create_app(roomy)) as client:
        assert upload(client).status_code == 200  # EDGEPOS_MAX_BODY_BYTES does not apply to this route


def test_gnss_tight_on_the_real_recording_end_to_end(client):
    assert upload(client).status_code == 200
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    fixes = []
    for seq, first in enumerate(range(0, 10, 4), start=1):
        items = measurements(first, min(4, 10 - first))
        response = post(client, session_id, token, seq, items)
        assert response.status_code == 200, response.text
        batch = response.json()["fixes"]
        assert len(batch) == min(4, 10 - first)
        for fix in batch:
            uses = fix["measurements"]
            assert all(use["type"] == "pseudorange" for use in uses) and len(uses) == 15
            assert all(use["used"] or use["reason"] for use in uses)
        fixes.extend(batch)
    assert [fix["status"] for fix in fixes] == ["initialised"] + ["tracking"] * 9
    assert [fix["t"] for fix in fixes] == [t % 604800 for t, _ in epochs()]
    errors = []
    for fix in fixes:
        assert -math.pi / 2 <= fix["latitude"] <= math.pi / 2 and -math.pi <= fix["longitude"] <= math.pi
        assert math.degrees(fix["latitude"]) == pytest.approx(41.65, abs=0.2)  # ~30 km NNE of Barcelona
        assert math.degrees(fix["longitude"]) == pytest.approx(2.35, abs=0.3)
        assert 0.0 < fix["height"] < 1000.0
        error = horizontal_error(fix)
        if error is not None:
            errors.append(error)
    assert len(errors) >= 8
    assert max(errors) < 10.0, errors  # a single-point fix here is within a few metres
    described = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    assert described["epochs"] == 10 and described["initialised"]
    assert described["last_fix"]["height"] == fixes[-1]["height"]


def test_fixes_are_on_the_configured_site_frame(tmp_path):
    origin = {"origin_lat": 41.6, "origin_lon": 2.3, "origin_height": 100.0}
    with TestClient(create_app(make_settings(tmp_path, **origin))) as client:
        assert upload(client).status_code == 200
        session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
        fix = post(client, session_id, token, 1, measurements(0, 1)).json()["fixes"][0]
    # x east, y north of the configured origin, consistent with the fix's own latitude/longitude.
    north = (fix["latitude"] - math.radians(41.6)) * 6.37e6
    east = (fix["longitude"] - math.radians(2.3)) * 6.37e6 * math.cos(math.radians(41.6))
    assert fix["x"] == pytest.approx(east, rel=0.01, abs=50.0)
    assert fix["y"] == pytest.approx(north, rel=0.01, abs=50.0)


def test_pseudoranges_without_a_satellite_state_are_refused(client):
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    items = measurements(0, 1)
    error = assert_error(post(client, session_id, token, 1, items), 422, "invalid_request")
    assert "no ephemerides are loaded" in error["message"]
    assert [p["index"] for p in error["problems"]] == list(range(len(items)))
    assert error["problems"][0]["field"] == "measurements[0].sat_position"
    assert "PUT /v1/ephemerides" in error["problems"][0]["reason"]

    assert upload(client).status_code == 200
    unknown = {**items[0], "system": "C", "prn": 60}  # no BeiDou C60 in the file
    error = assert_error(post(client, session_id, token, 1, [*items, unknown]), 422, "invalid_request")
    (problem,) = error["problems"]
    assert problem["index"] == len(items) and problem["field"] == f"measurements[{len(items)}].prn"
    assert "C60" in problem["reason"]
    late = [{**m, "t": m["t"] + 3 * 86400.0} for m in items]  # three days after the file's window
    error = assert_error(post(client, session_id, token, 1, late), 422, "invalid_request")
    assert len(error["problems"]) == len(items)
    error = assert_error(post(client, session_id, token, 1, [*items, items[3]]), 422, "invalid_request")
    (problem,) = error["problems"]
    assert problem["field"] == f"measurements[{len(items)}].prn" and "measurements[3]" in problem["reason"]
    half = {**items[0], "sat_position": [1.5e7, 1.5e7, 1.0e7]}
    error = assert_error(post(client, session_id, token, 1, [half]), 422, "invalid_request")
    assert error["problems"][0]["field"] == "measurements[0].sat_clock"
    described = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    assert described["last_seq"] == 0 and described["epochs"] == 0  # nothing was applied
    # A constellation the session does not use needs no ephemeris: reported unused, not refused.
    galileo = {**items[0], "system": "E", "prn": 36}
    response = post(client, session_id, token, 1, [*items, galileo])
    assert response.status_code == 200, response.text
    (use,) = [u for u in response.json()["fixes"][0]["measurements"] if u["index"] == len(items)]
    assert not use["used"] and "options.systems" in use["reason"]


def test_client_computed_satellite_states_need_no_ephemerides(client):
    """A client that computes sat_position and sat_clock itself gets the same fix as the service's own."""
    items = measurements(0, 1)
    sent, gpst = _with_satellite_states(items)
    options = {**QUICK, "gps_week": int(gpst // 604800), "ionosphere": False}
    session_id, token = open_session(client, pipeline="gnss_tight", options=options)
    own = post(client, session_id, token, 1, sent)
    assert own.status_code == 200, own.text
    assert upload(client).status_code == 200
    session_id, token = open_session(client, pipeline="gnss_tight", options=options)
    served = post(client, session_id, token, 1, items).json()["fixes"][0]
    mine = own.json()["fixes"][0]
    assert mine["status"] == "initialised"
    assert mine["latitude"] == pytest.approx(served["latitude"], abs=1e-9)  # ~6 mm
    assert mine["height"] == pytest.approx(served["height"], abs=0.05)


@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"system": "R"}, "measurements[0].system"),
        ({"prn": 0}, "measurements[0].prn"),
        ({"prn": 5.0}, "measurements[0].prn"),
        ({"pseudorange_m": 12.0}, "measurements[0].pseudorange_m"),
        ({"cn0_dbhz": -1.0}, "measurements[0].cn0_dbhz"),
        ({"t": 604800.0}, "measurements[0].t"),
        ({"sat_position": [1.0, 2.0]}, "measurements[0].sat_position"),
        ({"sat_clock": 0.5}, "measurements[0].sat_clock"),
        ({"doppler_hz": 20000.5}, "measurements[0].doppler_hz"),
        ({"doppler_hz": -25000.0}, "measurements[0].doppler_hz"),
        ({"doppler_hz": "1200"}, "measurements[0].doppler_hz"),
        ({"carrier_cycles": 1.0e10}, "measurements[0].carrier_cycles"),
        ({"carrier_cycles": -2.0e10}, "measurements[0].carrier_cycles"),
        ({"carrier_cycles": "1.5e8"}, "measurements[0].carrier_cycles"),
        ({"lli": 8}, "measurements[0].lli"),
        ({"lli": -1}, "measurements[0].lli"),
        ({"lli": 1.5}, "measurements[0].lli"),
        ({"lli": True}, "measurements[0].lli"),
        ({"sat_velocity": [1.0, 2.0]}, "measurements[0].sat_velocity"),
        ({"sat_velocity": [2.0e4, 0.0, 0.0], "sat_clock_drift": 0.0}, "measurements[0].sat_velocity[0]"),
        ({"sat_clock_drift": 1.0e-3}, "measurements[0].sat_clock_drift"),
        ({"extra": 1}, "measurements[0].extra"),
    ],
)
def test_bad_pseudorange_fields_are_named(client, change, field):
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    item = {**measurements(0, 1)[0], **change}
    error = assert_error(post(client, session_id, token, 1, [item]), 422, "invalid_request")
    assert field in [p["field"] for p in error["problems"]]
    assert all(p["index"] == 0 for p in error["problems"])


def test_nan_is_refused(client):
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    item = measurements(0, 1)[0]
    raw = (
        f'{{"seq": 1, "measurements": [{{"type": "pseudorange", "t": {item["t"]!r}, "system": "G", '
        f'"prn": {item["prn"]:d}, "pseudorange_m": NaN, "cn0_dbhz": 40.0}}]}}'
    )
    response = client.post(
        f"/v1/sessions/{session_id}/batches",
        content=raw,
        headers={**token, "Content-Type": "application/json"},
    )
    error = assert_error(response, 422, "invalid_request")
    assert error["problems"][0]["field"] == "measurements[0].pseudorange_m"


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_carrier_phase_is_refused_and_the_session_unchanged(client, value):
    assert upload(client).status_code == 200
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    first = post(client, session_id, token, 1, with_carrier(measurements(0, 1)))
    assert first.status_code == 200, first.text
    before = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    item = measurements(1, 1)[0]
    raw = (
        f'{{"seq": 2, "measurements": [{{"type": "pseudorange", "t": {item["t"]!r}, "system": "{item["system"]}", '
        f'"prn": {item["prn"]}, "pseudorange_m": {item["pseudorange_m"]!r}, "cn0_dbhz": 40.0, '
        f'"carrier_cycles": {value}, "lli": 0}}]}}'
    )
    response = client.post(
        f"/v1/sessions/{session_id}/batches",
        content=raw,
        headers={**token, "Content-Type": "application/json"},
    )
    error = assert_error(response, 422, "invalid_request")
    assert error["problems"][0]["field"] == "measurements[0].carrier_cycles"
    assert client.get(f"/v1/sessions/{session_id}", headers=token).json() == before


def test_carrier_phase_smooths_the_fixes_on_the_wire(client):
    """The recording's carrier phases with their LLI are accepted and change the fixes (Hatch smoothing, the
    default); with options.carrier_smoothing off the same batches give the fixes of code alone."""
    assert upload(client).status_code == 200
    fixes = {}
    for name, options, carrier in (
        ("hatch", QUICK, True),
        ("off", {**QUICK, "carrier_smoothing": "off"}, True),
        ("code", QUICK, False),
    ):
        session_id, token = open_session(client, pipeline="gnss_tight", options=options)
        got = []
        for seq in range(1, 7):
            items = with_doppler(measurements(seq - 1, 1))
            response = post(client, session_id, token, seq, with_carrier(items) if carrier else items)
            assert response.status_code == 200, response.text
            got.append(response.json()["fixes"][0])
        fixes[name] = [(f["latitude"], f["longitude"]) for f in got]
    assert fixes["off"] == fixes["code"]
    assert fixes["hatch"] != fixes["code"]


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_non_finite_doppler_is_refused_and_the_session_unchanged(client, value):
    assert upload(client).status_code == 200
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    first = post(client, session_id, token, 1, with_doppler(measurements(0, 1)))
    assert first.status_code == 200, first.text
    before = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    item = with_doppler(measurements(1, 1))[0]
    raw = (
        f'{{"seq": 2, "measurements": [{{"type": "pseudorange", "t": {item["t"]!r}, "system": "{item["system"]}", '
        f'"prn": {item["prn"]}, "pseudorange_m": {item["pseudorange_m"]!r}, "cn0_dbhz": 40.0, '
        f'"doppler_hz": {value}}}]}}'
    )
    response = client.post(
        f"/v1/sessions/{session_id}/batches",
        content=raw,
        headers={**token, "Content-Type": "application/json"},
    )
    error = assert_error(response, 422, "invalid_request")
    assert error["problems"][0]["field"] == "measurements[0].doppler_hz"
    assert client.get(f"/v1/sessions/{session_id}", headers=token).json() == before


def test_dopplers_are_used_and_reported(client):
    """Dopplers on the wire enter the update and are reported per measurement; the same epochs with
    use_doppler off report every Doppler unused, saying why; a client-computed satellite state has no
    velocity, so its Doppler is reported unused with the reason."""
    assert upload(client).status_code == 200
    reports = {}
    for use_doppler in (True, False):
        session_id, token = open_session(
            client, pipeline="gnss_tight", options={**QUICK, "use_doppler": use_doppler}
        )
        for seq in range(1, 4):
            response = post(client, session_id, token, seq, with_doppler(measurements(seq - 1, 1)))
            assert response.status_code == 200, response.text
        reports[use_doppler] = response.json()["fixes"][0]
    on, off = reports[True]["measurements"], reports[False]["measurements"]
    assert all(use["doppler_used"] is not None for use in on + off)
    assert sum(use["doppler_used"] for use in on) >= 8
    assert all(use["doppler_used"] or use["doppler_reason"] for use in on)
    assert not any(use["doppler_used"] for use in off)
    assert all(use["doppler_reason"] == "options.use_doppler is off" for use in off)
    assert reports[True]["nis_dof"] > reports[False]["nis_dof"]
    sent, _ = _with_satellite_states(with_doppler(measurements(0, 1)))
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    (fix,) = post(client, session_id, token, 1, sent).json()["fixes"]
    assert all(
        use["doppler_used"] is False and "no satellite velocity" in use["doppler_reason"]
        for use in fix["measurements"]
    )
    # with the satellites' velocities and clock drifts sent too, the client's states carry the Dopplers
    sent, _ = _with_satellite_states(with_doppler(measurements(0, 1)), rates=True)
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    (fix,) = post(client, session_id, token, 1, sent).json()["fixes"]
    assert sum(use["doppler_used"] for use in fix["measurements"]) >= 8
    assert [use["doppler_used"] for use in fix["measurements"]] == [
        use["doppler_used"] for use in post_first_epoch(client, with_doppler(measurements(0, 1)))
    ]


def post_first_epoch(client, items: list[dict]) -> list[dict]:
    """The per-measurement report of the first epoch of a new session (ephemerides loaded)."""
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    response = post(client, session_id, token, 1, items)
    assert response.status_code == 200, response.text
    (fix,) = response.json()["fixes"]
    return list(fix["measurements"])


@pytest.mark.parametrize(
    ("change", "field", "words"),
    [
        ({"sat_velocity": [100.0, 200.0, 300.0]}, "sat_clock_drift", "go together"),
        ({"sat_clock_drift": 1.0e-12}, "sat_velocity", "go together"),
    ],
)
def test_a_satellite_velocity_comes_with_its_clock_drift(client, change, field, words):
    """sat_velocity and sat_clock_drift go together: one without the other is refused naming the missing
    one, and the session is unchanged."""
    assert upload(client).status_code == 200
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    before = client.get(f"/v1/sessions/{session_id}", headers=token).json()
    sent, _ = _with_satellite_states(measurements(0, 1))
    error = assert_error(post(client, session_id, token, 1, [{**sent[0], **change}]), 422, "invalid_request")
    problems = [p for p in error["problems"] if p["field"] == f"measurements[0].{field}"]
    assert problems and words in problems[0]["reason"]
    assert client.get(f"/v1/sessions/{session_id}", headers=token).json() == before


def test_a_satellite_velocity_needs_the_satellites_position(client):
    assert upload(client).status_code == 200
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    item = {**measurements(0, 1)[0], "sat_velocity": [100.0, 200.0, 300.0], "sat_clock_drift": 0.0}
    error = assert_error(post(client, session_id, token, 1, [item]), 422, "invalid_request")
    reasons = {p["field"]: p["reason"] for p in error["problems"]}
    assert "sat_position and sat_clock" in reasons["measurements[0].sat_velocity"]


def test_an_epoch_too_costly_with_its_dopplers_is_refused_saying_what_to_change(tmp_path):
    """On a server whose CPU budget per batch sits between the predicted cost of one epoch of 40 pseudoranges
    at the defaults (UPF, 200 particles) without their Dopplers and with them (each Doppler adds an update
    row), that epoch with Dopplers is refused: 422 saying so and what to change, the session unchanged."""
    pipeline = get_pipeline("gnss_tight")
    options = pipeline.resolve_options({"seed": 1})
    template = measurements(0, 1)[0]
    sats = [("G", prn) for prn in range(1, 33)] + [("C", prn) for prn in range(1, 9)]
    epoch = [{**template, "system": system, "prn": prn, "doppler_hz": 100.0} for system, prn in sats]
    with_doppler = cost.batch_cost_s("gnss_tight", options, [_observation(m) for m in epoch])
    without = max(
        cost.batch_cost_s("gnss_tight", options, [_observation({**m, "doppler_hz": None}) for m in epoch]),
        cost.epoch_cost_s("gnss_tight", options, {"pseudorange": 40, "riss": 4}),  # what a session must fit
    )
    assert without < with_doppler
    budget_ms = 1e3 * (without + with_doppler) / 2
    with TestClient(create_app(make_settings(tmp_path, batch_cpu_budget_ms=budget_ms))) as client:
        assert upload(client).status_code == 200
        session_id, token = open_session(client, pipeline="gnss_tight", options={"seed": 1})
        error = assert_error(post(client, session_id, token, 1, epoch), 422, "invalid_request")
        assert "too costly" in error["message"]
        assert "one epoch like these alone" in error["problems"][0]["reason"]
        assert "use_doppler" in error["problems"][0]["reason"]
        described = client.get(f"/v1/sessions/{session_id}", headers=token).json()
        assert described["last_seq"] == 0 and described["epochs"] == 0


def _observation(wire: dict) -> PseudorangeObservation:
    return PseudorangeObservation(
        wire["t"],
        wire["system"],
        wire["prn"],
        wire["pseudorange_m"],
        wire["cn0_dbhz"],
        doppler_hz=wire["doppler_hz"],
    )


def test_riss_samples_drive_the_motion_model(client):
    assert upload(client).status_code == 200
    session_id, token = open_session(client, pipeline="gnss_tight", options=QUICK)
    t0 = epochs()[0][0] % 604800
    riss = {"type": "riss", "t": t0, "wheel_speed": 0.5, "accel_x": 0.1, "accel_y": -0.05, "gyro_z": 0.01}
    response = post(client, session_id, token, 1, [riss, *measurements(0, 1)])
    assert response.status_code == 200, response.text
    (fix,) = response.json()["fixes"]
    assert fix["measurements"][0] == {"index": 0, "type": "riss", "used": True, "reason": None, **NO_DOPPLER}
    response = post(client, session_id, token, 2, [{**riss, "t": t0 + 1.0}, *measurements(1, 1)])
    assert response.status_code == 200, response.text
    assert response.json()["fixes"][0]["yaw_rate"] == 0.01
    error = assert_error(
        post(client, session_id, token, 3, [{**riss, "t": t0 + 2.0, "gyro_z": 11.0}]), 422, "invalid_request"
    )
    assert error["problems"][0]["field"] == "measurements[0].gyro_z"


def test_measurement_types_are_checked_against_the_pipeline(client):
    session_id, token = open_session(client)  # rsu_imu
    error = assert_error(post(client, session_id, token, 1, measurements(0, 1)[:1]), 422, "invalid_request")
    assert error["problems"][0]["field"] == "measurements[0].type"
    gnss_id, gnss_token = open_session(client, pipeline="gnss_tight", options=QUICK)
    gyro = {"type": "gyro", "t": 1.0, "yaw_rate": 0.1}
    error = assert_error(post(client, gnss_id, gnss_token, 1, [gyro]), 422, "invalid_request")
    assert error["problems"][0]["field"] == "measurements[0].type"


def test_pipelines_list_gnss_tight_with_its_options(client):
    listed = {p["name"]: p for p in client.get("/v1/pipelines").json()["pipelines"]}
    gnss = listed["gnss_tight"]
    assert gnss["measurement_types"] == ["pseudorange", "riss"]
    options = {o["name"]: o for o in gnss["options"]}
    assert options["filter"]["default"] == "upf" and set(options["filter"]["choices"]) == {"upf", "pf", "ukf"}
    assert options["particles"]["minimum"] == 10 and options["particles"]["maximum"] == 700
    assert options["systems"]["type"] == "string[]" and options["systems"]["default"] == ["G", "C", "E"]
    assert all(o["description"] for o in gnss["options"])
    error = assert_error(
        client.post(
            "/v1/sessions",
            json={"vehicle_id": "c", "pipeline": "gnss_tight", "options": {"particles": 1}},
            headers=ADMIN,
        ),
        422,
        "invalid_request",
    )
    assert error["problems"][0]["field"] == "options.particles"


def test_served_fixes_equal_the_pipeline_bit_for_bit(client):
    """The service hands the pipeline the same ephemerides and observations as a direct call: the UPF's
    fixes over the wire are the in-process pipeline's, float for float (the state bytes too)."""
    from edgepos.core.observations import PseudorangeObservation
    from edgepos.pipelines.base import StaticEnvironment
    from edgepos.pipelines.registry import get_pipeline

    options = {"filter": "upf", "particles": 50, "seed": 11, "systems": ["G", "C"]}
    assert upload(client).status_code == 200
    session_id, token = open_session(client, pipeline="gnss_tight", options=options)
    pipeline = get_pipeline("gnss_tight")
    environment = StaticEnvironment(navigation=parse_ephemerides(nav_text()))
    state = pipeline.create(pipeline.resolve_options(options), None)
    for seq, first in enumerate(range(0, 10, 5), start=1):
        items = measurements(first, 5)
        observations = [
            PseudorangeObservation(m["t"], m["system"], m["prn"], m["pseudorange_m"], m["cn0_dbhz"])
            for m in items
        ]
        expected, state = pipeline.process(state, observations, environment)
        served = post(client, session_id, token, seq, items, include_state=True).json()["fixes"]
        assert len(served) == len(expected) == 5
        for got, fix in zip(served, expected, strict=True):
            for name in ("t", "x", "y", "vx", "vy", "latitude", "longitude", "height", "nis"):
                value = getattr(fix, name)
                assert got[name] == value and (value is None or got[name].hex() == value.hex()), name
            assert got["state"]["mean"] == fix.state and got["status"] == fix.status
    stored = client.portal.call(client.app.state.context.store.get, session_id)
    assert stored.state == state
