"""No pseudorange batch that passes the schema gets a 500: random subsets, offsets and C/N0 of the real
recording's pseudoranges, against every filter of gnss_tight."""

from __future__ import annotations

import pytest
from apihelp import ADMIN, make_settings
from edgepos.api.app import create_app
from fastapi.testclient import TestClient
from gnsswire import epochs, nav_text
from hypothesis import HealthCheck, given, settings
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


epoch_edit = st.tuples(
    st.lists(st.booleans(), min_size=15, max_size=15),  # which satellites to keep
    st.lists(st.sampled_from([0.0, 0.0, 0.0, 30.0, -500.0, 1.0e4, -2.0e5]), min_size=15, max_size=15),
    st.lists(st.floats(0.0, 100.0), min_size=15, max_size=15),
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    options=st.sampled_from(FILTERS),
    fuzzy=st.booleans(),
    edits=st.lists(epoch_edit, min_size=1, max_size=4),
    skip=st.integers(0, 5),
)
def test_no_batch_of_valid_pseudoranges_gets_a_500(gnss_client, options, fuzzy, edits, skip):
    created = gnss_client.post(
        "/v1/sessions",
        json={
            "vehicle_id": "fuzz",
            "pipeline": "gnss_tight",
            "options": {**options, "fuzzy": fuzzy, "seed": 3},
        },
    )
    assert created.status_code == 201, created.text
    session_id, token = created.json()["session_id"], {"Authorization": f"Bearer {created.json()['token']}"}
    items = []
    for number, (keep, offsets, cn0s) in enumerate(edits):
        _, epoch = epochs()[min(number * (skip + 1), 9)]
        for k, measurement in enumerate(epoch):
            if keep[k % 15]:
                pseudorange = min(max(measurement["pseudorange_m"] + offsets[k % 15], 1.0e6), 1.0e8)
                items.append({**measurement, "pseudorange_m": pseudorange, "cn0_dbhz": cn0s[k % 15]})
    if not items:
        return
    response = gnss_client.post(f"/v1/sessions/{session_id}/batches", json={"seq": 1, "measurements": items},
                                headers=token)
    assert response.status_code in (200, 422), response.text
    if response.status_code == 200:
        for fix in response.json()["fixes"]:
            assert len(fix["measurements"]) == sum(1 for m in items if m["t"] == fix["t"])
