"""No request that passes the schema gets a 500: random subsets, offsets and C/N0 of the real recording's
pseudoranges, repeated satellites, wild RISS samples, split over two batches, against every gnss_tight
filter. (It found a singular-geometry crash in the least-squares initialisation and duplicate satellites
that went unreported.)"""

from __future__ import annotations

import pytest
from apihelp import ADMIN, make_settings
from edgepos.api.app import create_app
from fastapi.testclient import TestClient
from gnsswire import epochs, nav_text
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

FILTERS = [{"filter": "ukf"}, {"filter": "pf", "particles": 10}, {"filter": "upf", "particles": 10}]


@pytest.fixture(scope="module")
def gnss_client(tmp_path_factory: pytest.TempPathFactory):
    app = create_app(make_settings(tmp_path_factory.mktemp("fuzz"), rate_limit_per_s=0))
    with TestClient(app) as client:
        headers = {**ADMIN, "Content-Type": "text/plain"}
        response = client.put("/v1/ephemerides", content=nav_text(), headers=headers)
        assert response.status_code == 200
        yield client


riss = st.fixed_dictionaries(
    {
        "wheel_speed": st.floats(-100.0, 100.0),
        "accel_x": st.floats(-50.0, 50.0),
        "accel_y": st.floats(-50.0, 50.0),
        "gyro_z": st.floats(-10.0, 10.0),
    }
)
epoch_edit = st.tuples(
    st.lists(st.sampled_from([True, True, True, False]), min_size=15, max_size=15),  # satellites kept
    st.lists(st.sampled_from([0.0] * 12 + [30.0, -500.0, 1.0e4, -2.0e5]), min_size=15, max_size=15),
    st.lists(st.floats(0.0, 100.0), min_size=15, max_size=15),
    st.none() | riss,
    st.sampled_from([False] * 9 + [True]),  # repeat the epoch's first kept pseudorange
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    options=st.sampled_from(FILTERS),
    fuzzy=st.booleans(),
    edits=st.lists(epoch_edit, min_size=1, max_size=5),
    step=st.integers(1, 2),
    split=st.integers(0, 6),
)
def test_no_schema_valid_gnss_batch_gets_a_500(gnss_client, options, fuzzy, edits, step, split):
    created = gnss_client.post(
        "/v1/sessions",
        json={
            "vehicle_id": "fuzz",
            "pipeline": "gnss_tight",
            "options": {**options, "fuzzy": fuzzy, "seed": 3},
        },
        headers=ADMIN,
    )
    assert created.status_code == 201, created.text
    session_id, token = created.json()["session_id"], {"Authorization": f"Bearer {created.json()['token']}"}
    batches: list[list[dict]] = [[], []]
    for number, (keep, offsets, cn0s, sample, repeat) in enumerate(edits):
        t, epoch = epochs()[min(number * step, 9)]
        items = [
            {
                **measurement,
                "pseudorange_m": min(max(measurement["pseudorange_m"] + offsets[k], 1.0e6), 1.0e8),
                "cn0_dbhz": cn0s[k],
            }
            for k, measurement in enumerate(epoch)
            if keep[k]
        ]
        if repeat and items:
            items.append(items[0])
        if sample is not None:
            items.append({"type": "riss", "t": t % 604800, **sample})
        batches[number >= split].extend(items)
    seq = 0
    for items in batches:
        if not items:
            continue
        response = gnss_client.post(
            f"/v1/sessions/{session_id}/batches", json={"seq": seq + 1, "measurements": items}, headers=token
        )
        assert response.status_code in (200, 422), response.text
        event(f"batch answered {response.status_code}")
        if response.status_code != 200:
            continue
        seq += 1
        for fix in response.json()["fixes"]:
            event(f"fix {fix['status']}")
            assert len(fix["measurements"]) == sum(1 for m in items if m["t"] == fix["t"])
