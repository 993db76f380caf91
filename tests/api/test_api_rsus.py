"""The RSU registry: upserts, reads, deletes, and who may do each."""

from __future__ import annotations

from apihelp import ADMIN, assert_error, bearer, open_session, scenario

NEW = {"id": "K-1", "x": 12.5, "y": -3.0, "range_std": 0.5, "bearing_std": None, "radius": 120.0}


def test_bulk_upsert_then_list_sorted_by_id(client):
    listed = client.get("/v1/rsus", headers=ADMIN)
    assert listed.status_code == 200
    rsus = listed.json()["rsus"]
    assert [r["id"] for r in rsus] == sorted(r.id for r in scenario().rsus)
    first = next(r for r in scenario().rsus if r.id == rsus[0]["id"])
    assert rsus[0] == {
        "id": first.id,
        "x": first.x,
        "y": first.y,
        "range_std": first.range_std,
        "bearing_std": first.bearing_std,
        "radius": first.radius,
    }


def test_bulk_upsert_counts_and_replaces(client):
    response = client.put("/v1/rsus", json={"rsus": [NEW, {**NEW, "id": "K-2", "x": 1.0}]}, headers=ADMIN)
    assert response.status_code == 200
    assert response.json() == {"upserted": 2}
    response = client.put("/v1/rsus", json={"rsus": [{**NEW, "x": 99.0}]}, headers=ADMIN)
    assert response.json() == {"upserted": 1}
    assert client.get("/v1/rsus/K-1", headers=ADMIN).json()["x"] == 99.0


def test_bulk_upsert_refuses_duplicate_ids_and_writes_nothing(client):
    response = client.put("/v1/rsus", json={"rsus": [NEW, {**NEW, "x": 5.0}]}, headers=ADMIN)
    error = assert_error(response, 422, "invalid_request")
    assert {p["field"] for p in error["problems"]} == {"rsus[0].id", "rsus[1].id"}
    assert_error(client.get("/v1/rsus/K-1", headers=ADMIN), 404, "not_found")


def test_put_one_with_or_without_matching_id(client):
    body = {k: v for k, v in NEW.items() if k != "id"}
    response = client.put("/v1/rsus/K-1", json=body, headers=ADMIN)
    assert response.status_code == 200
    assert response.json() == NEW
    response = client.put("/v1/rsus/K-1", json={**body, "id": "K-1", "y": 4.0}, headers=ADMIN)
    assert response.status_code == 200 and response.json()["y"] == 4.0
    assert client.get("/v1/rsus/K-1", headers=ADMIN).json() == {**NEW, "y": 4.0}


def test_put_one_with_another_id_is_refused(client):
    body = {**NEW, "id": "other"}
    error = assert_error(client.put("/v1/rsus/K-1", json=body, headers=ADMIN), 422, "invalid_request")
    assert error["problems"] == [{"index": None, "field": "id", "reason": error["problems"][0]["reason"]}]
    assert_error(client.get("/v1/rsus/K-1", headers=ADMIN), 404, "not_found")


def test_delete(client):
    rsu_id = scenario().rsus[0].id
    assert client.delete(f"/v1/rsus/{rsu_id}", headers=ADMIN).status_code == 204
    assert_error(client.get(f"/v1/rsus/{rsu_id}", headers=ADMIN), 404, "not_found")
    assert_error(client.delete(f"/v1/rsus/{rsu_id}", headers=ADMIN), 404, "not_found")


def test_invalid_rsus_list_every_problem(client):
    bad = [
        {**NEW, "range_std": -1.0},
        {**NEW, "id": "has space"},
        {**NEW, "radius": 0},
        {k: v for k, v in NEW.items() if k != "x"},
        {**NEW, "extra": 1},
    ]
    error = assert_error(client.put("/v1/rsus", json={"rsus": bad}, headers=ADMIN), 422, "invalid_request")
    fields = {p["field"] for p in error["problems"]}
    assert {"rsus[0].range_std", "rsus[1].id", "rsus[2].radius", "rsus[3].x", "rsus[4].extra"} <= fields


def test_non_finite_json_literals_are_refused(client):
    for literal in ("NaN", "Infinity", "-Infinity"):
        content = '{"rsus": [{"id": "K", "x": ' + literal + ', "y": 0}]}'
        response = client.put(
            "/v1/rsus", content=content, headers={**ADMIN, "content-type": "application/json"}
        )
        error = assert_error(response, 422, "invalid_request")
        assert error["problems"][0]["field"] == "rsus[0].x"


def test_bad_path_id_is_refused(client):
    error = assert_error(client.get("/v1/rsus/bad%20id", headers=ADMIN), 422, "invalid_request")
    assert error["problems"][0]["field"] == "rsu_id"


def test_writes_need_the_admin_key(client):
    _, token = open_session(client)
    assert_error(client.put("/v1/rsus", json={"rsus": [NEW]}, headers=token), 403, "forbidden")
    assert_error(client.put("/v1/rsus/K-1", json=NEW, headers=token), 403, "forbidden")
    assert_error(client.delete(f"/v1/rsus/{scenario().rsus[0].id}", headers=token), 403, "forbidden")
    assert_error(client.put("/v1/rsus", json={"rsus": [NEW]}), 401, "unauthorized")
    assert_error(client.put("/v1/rsus", json={"rsus": [NEW]}, headers=bearer("wrong")), 401, "unauthorized")
    assert_error(client.get("/v1/rsus/K-1", headers=ADMIN), 404, "not_found")


def test_reads_need_any_valid_credential(client):
    _, token = open_session(client)
    assert client.get("/v1/rsus", headers=token).status_code == 200
    assert client.get(f"/v1/rsus/{scenario().rsus[0].id}", headers=token).status_code == 200
    response = assert_error(client.get("/v1/rsus"), 401, "unauthorized")
    assert response["problems"] == []
    assert_error(client.get("/v1/rsus", headers=bearer("0" * 32 + ".forged-secret")), 401, "unauthorized")
    assert_error(
        client.get("/v1/rsus", headers={"Authorization": f"Basic {ADMIN['Authorization'][7:]}"}),
        401,
        "unauthorized",
    )
