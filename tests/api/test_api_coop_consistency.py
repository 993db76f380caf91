"""The cooperative pipelines' consistency options over HTTP: out of bounds is a 422 naming the option,
and GET /v1/pipelines documents the bound's options with their defaults."""

from __future__ import annotations

import pytest
from apihelp import ADMIN, assert_error


@pytest.mark.parametrize("pipeline", ["v2v_coop", "v2x_federated"])
@pytest.mark.parametrize(
    "options",
    [
        {"consistency_risk_share": 0.0},
        {"consistency_risk_share": 1.0},
        {"consistency_risk_share": -0.25},
        {"consistency_bound": "yes"},
    ],
)
def test_consistency_bound_options_out_of_bounds_are_422_naming_the_option(client, pipeline, options):
    response = client.post(
        "/v1/sessions", json={"vehicle_id": "car-9", "pipeline": pipeline, "options": options}, headers=ADMIN
    )
    error = assert_error(response, 422, "invalid_request")
    (name,) = options
    assert f"options.{name}" in {p["field"] for p in error["problems"]}, error


@pytest.mark.parametrize("pipeline", ["v2v_coop", "v2x_federated"])
def test_the_bound_options_are_documented_with_their_defaults(client, pipeline):
    pipelines = {p["name"]: p for p in client.get("/v1/pipelines").json()["pipelines"]}
    options = {o["name"]: o for o in pipelines[pipeline]["options"]}
    assert options["consistency_bound"]["default"] is True
    share = options["consistency_risk_share"]
    assert share["default"] == 0.25 and (share["minimum"], share["maximum"]) == (0.01, 0.99)
    assert options["consistency_scale"]["default"] is False
