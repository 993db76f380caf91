"""No 5xx and no non-finite number from any option set a client may send: hypothesis draws each pipeline's
options from what ``GET /v1/pipelines`` publishes (every number within its minimum..maximum, the extremes
and their neighbours included; integers, booleans, choices, subsets of choices, transition matrices and
probability vectors, ``model_params``/``filter_params`` from the core's parameter tables that the option
descriptions list) and an initial state within ``InitialStateIn``'s bounds in openapi.json, opens a
session and sends that pipeline's one normal batch.

Every answer must be below 500; a 2xx answer holds only finite numbers; a refusal is the standard error
body (``invalid_request`` for options outside the published bounds, ``estimation_failed`` with the
session unchanged when the filter cannot compute the batch). A value just outside a published bound
must be refused naming its field.

Cases: ``CI`` set: 5,000, spread over the pipelines by ``one_of``; locally 300 (``OPTION_FUZZ_EXAMPLES``
overrides both). Each case is one session and one short batch (3-4 epochs, particles mostly few), so
5,000 take about 1.5 minutes. It found, besides the issue's overflows (noise options without an upper
bound, rsu_imu's Singer sigma) and 0/0 yaw rate: an empty model list with empty initial probabilities
(a 500), initial-state stds so small that their squares are 0 (a singular covariance), UKF alphas far
from the unscented transform's range, and gnss_tight's clock process noise, indefinite for a small
clock_bias_psd (the particle filters could not draw from it).
"""

from __future__ import annotations

import functools
import itertools
import json
import math
import os
from collections.abc import Iterator
from typing import Any

import pytest
from apihelp import ADMIN, batch_body, make_settings, rsu_payload
from edgepos.api.app import create_app
from edgepos.core.filters import FILTERS
from edgepos.core.motion import MOTION_MODELS
from fastapi.testclient import TestClient
from gnsswire import epochs as gnss_epochs
from gnsswire import nav_text
from hypothesis import HealthCheck, event, example, given, settings
from hypothesis import strategies as st

EXAMPLES = int(os.environ.get("OPTION_FUZZ_EXAMPLES") or (5000 if os.environ.get("CI") else 300))
PEER = "fuzz-peer"
_vehicle_numbers = itertools.count()


# -- the normal batch of each pipeline -----------------------------------------------------------
def _kinematic_batch(with_rsu: bool) -> list[dict[str, Any]]:
    """Four epochs 0.2 s apart of a car driving east at 10 m/s along y = 0 next to the peer (y = 3.5):
    GNSS fixes, gyro, odometer (speed and distance readings), a range to the peer (inside its published
    history, and once 0.2 s past it) and, for v2x_federated, a range to RSU S+000 at (0, -3.875)."""
    items: list[dict[str, Any]] = []
    for k in range(4):
        t = round(0.2 * k, 1)
        x = 10.0 * t
        items.append({"type": "gnss_fix", "t": t, "x": x + 0.3 * (-1) ** k, "y": 0.2 * (-1) ** (k // 2)})
        items.append({"type": "gyro", "t": t, "yaw_rate": 0.01})
        items.append({"type": "odometer", "t": t, **({"speed": 10.0} if k % 2 else {"distance": 2.0})})
        if k:
            items.append({"type": "v2v_range", "t": t, "peer_vehicle_id": PEER, "range": 3.6})
        if with_rsu:
            items.append(
                {"type": "rsu_range", "t": t, "rsu_id": "S+000", "range": math.hypot(x, 3.875) + 0.2}
            )
    return items


def _gnss_batch() -> list[dict[str, Any]]:
    """The first two epochs of the real recording's GPS + BeiDou pseudoranges (the first initialises, the
    second is filtered), with a RISS sample each."""
    items: list[dict[str, Any]] = []
    for _, epoch in gnss_epochs()[:2]:
        items.extend(epoch)
        items.append(
            {
                "type": "riss",
                "t": epoch[0]["t"],
                "wheel_speed": 5.0,
                "accel_x": 0.1,
                "accel_y": 0.0,
                "gyro_z": 0.01,
            }
        )
    return items


BATCHES = {
    "rsu_imu": batch_body(1, 0, 3)["measurements"],  # the paper's scenario: 0.05 s epochs, 4 RSUs and a gyro
    "v2v_coop": _kinematic_batch(with_rsu=False),
    "v2x_federated": _kinematic_batch(with_rsu=True),
    "gnss_tight": _gnss_batch(),
}


# -- the app and what it publishes ---------------------------------------------------------------
PUBLISHED: dict[str, Any] = {}
"""GET /v1/pipelines by pipeline name, and InitialStateIn's properties from openapi.json (filled by the
fixture before the first example is drawn)."""


@pytest.fixture(scope="module")
def fuzz_client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    """One app for every example: the paper's RSUs, the recording's ephemerides, and a peer vehicle whose
    session has published a track for the v2v ranges."""
    # Access logs off (they cost a third of a request here); sessions are not deleted (a request less per case).
    settings = make_settings(
        tmp_path_factory.mktemp("option-fuzz"), rate_limit_per_s=0, max_sessions=10**7, log_level="warning"
    )
    app = create_app(settings)
    with TestClient(app, raise_server_exceptions=False) as client:
        assert client.put("/v1/rsus", json=rsu_payload(), headers=ADMIN).status_code == 200
        headers = {**ADMIN, "Content-Type": "text/plain"}
        assert client.put("/v1/ephemerides", content=nav_text(), headers=headers).status_code == 200
        peer = client.post(
            "/v1/sessions",
            json={"vehicle_id": PEER, "pipeline": "v2v_coop", "options": {"method": "gps_dr"}},
            headers=ADMIN,
        )
        assert peer.status_code == 201, peer.text
        track = [
            {"type": "gnss_fix", "t": round(0.2 * k, 1), "x": 2.0 * k, "y": 3.5} for k in range(3)
        ]  # t 0 .. 0.4: the car's range at t = 0.6 reads the peer predicted 0.2 s past its last point
        token = {"Authorization": f"Bearer {peer.json()['token']}"}
        response = client.post(
            f"/v1/sessions/{peer.json()['session_id']}/batches",
            json={"seq": 1, "measurements": track},
            headers=token,
        )
        assert response.status_code == 200, response.text
        listing = client.get("/v1/pipelines").json()["pipelines"]
        PUBLISHED["pipelines"] = {p["name"]: p for p in listing}
        schemas = client.get("/openapi.json").json()["components"]["schemas"]
        PUBLISHED["initial_state"] = schemas["InitialStateIn"]["properties"]
        yield client


# -- strategies from the published schema --------------------------------------------------------
@functools.cache
def bounded_floats(low: float, high: float) -> st.SearchStrategy[float]:
    """Floats in [low, high]: the bounds, their neighbours, uniform, and (for positive ranges spanning
    decades) log-uniform draws. (Strategies are cached: building them costs more than drawing.)"""
    edges = {low, high, math.nextafter(low, high), math.nextafter(high, low)}
    if low != 0.0:
        edges.add(min(high, low * (1.0 + 1e-9) if low > 0 else low * (1.0 - 1e-9)))
    strategies = [st.sampled_from(sorted(edges)), st.floats(low, high)]
    if low > 0.0 and high / low > 100.0:
        strategies.append(
            st.floats(math.log10(low), math.log10(high)).map(lambda e: min(high, max(low, 10.0**e)))
        )
    return st.one_of(*strategies)


@functools.cache
def bounded_integers(low: int, high: int) -> st.SearchStrategy[int]:
    """Integers in [low, high], mostly near the low end (particles: the cost of a case grows with them),
    the bounds themselves always reachable."""
    small = st.integers(low, min(high, low + 40))
    return st.one_of(small, small, small, st.sampled_from([low, high]), st.integers(low, high))


@functools.cache
def probability_vectors(size: int) -> st.SearchStrategy[list[float]]:
    """Non-negative vectors summing to 1: one-hot, uniform, or normalised draws (exact zeros included)."""
    if size == 0:
        return st.just([])
    one_hot = st.integers(0, size - 1).map(lambda k: [1.0 if i == k else 0.0 for i in range(size)])
    entry = st.sampled_from([0.0, 1e-300, 1e-9, 0.5, 1.0]) | st.floats(0.0, 1.0)
    drawn = st.lists(entry, min_size=size, max_size=size)
    normalised = drawn.map(lambda v: [x / sum(v) for x in v] if sum(v) > 0.0 else [1.0 / size] * size)
    return st.one_of(one_hot, st.just([1.0 / size] * size), normalised)


@functools.cache
def stochastic_matrices(size: int) -> st.SearchStrategy[list[list[float]]]:
    return st.lists(probability_vectors(size), min_size=size, max_size=size)


@functools.cache
def parameter_values(owner: str) -> st.SearchStrategy[dict[str, Any]]:
    """A subset of a motion model's or filter's parameters (``core.parameters`` tables, as the option
    descriptions list them), each within its bounds."""
    specs = (MOTION_MODELS.get(owner) or FILTERS[owner]).parameters
    entries: dict[str, st.SearchStrategy[Any]] = {}
    for spec in specs:
        if spec.choices is not None:
            entries[spec.name] = st.sampled_from(spec.choices)
        else:
            values = bounded_floats(spec.minimum, spec.maximum)
            entries[spec.name] = (st.none() | values) if spec.nullable else values
    return st.fixed_dictionaries({}, optional=entries)


@functools.cache
def subsets(values: tuple[str, ...]) -> st.SearchStrategy[list[str]]:
    return st.lists(st.sampled_from(values), unique=True) if values else st.just([])


_SHAPED = ("matrix", "number[]", "object")
"""Option types whose shape follows other options (transition and model_params by models): drawn last."""


@functools.cache
def _independent_options(pipeline: str) -> st.SearchStrategy[dict[str, Any]]:
    """Any subset of the pipeline's other options, each value within what GET /v1/pipelines publishes."""
    optional = {}
    for option in PUBLISHED["pipelines"][pipeline]["options"]:
        if option["type"] in _SHAPED:
            continue
        kind, low, high, choices = option["type"], option["minimum"], option["maximum"], option["choices"]
        if kind == "number":
            values: st.SearchStrategy[Any] = bounded_floats(low, high)
        elif kind == "integer":
            values = bounded_integers(int(low), int(high))
        elif kind == "boolean":
            values = st.booleans()
        elif kind == "string":
            values = st.sampled_from(choices) if choices else st.just(option["default"])
        elif kind == "string[]":
            values = subsets(tuple(choices)) if choices else st.just(option["default"])
        else:
            raise AssertionError(f"option type {kind!r} has no strategy: add one")
        optional[option["name"]] = (st.none() | values) if option["default"] is None else values
    return st.fixed_dictionaries({}, optional=optional)


@st.composite
def option_sets(draw: st.DrawFn, name: str) -> tuple[dict[str, Any], str | None]:
    """Options of pipeline ``name`` and, when one value was pushed just outside its published bounds,
    the field the refusal must name."""
    published = {o["name"]: o for o in PUBLISHED["pipelines"][name]["options"]}
    options = dict(draw(_independent_options(name)))
    models = options.get("models", published.get("models", {}).get("default")) or []
    for option in published.values():
        if option["type"] not in _SHAPED or not draw(st.booleans()):
            continue
        if option["default"] is None and draw(st.sampled_from([False] * 5 + [True])):
            options[option["name"]] = None
        elif option["type"] in ("number[]", "matrix"):
            size = draw(st.sampled_from([len(models)] * 6 + [max(len(models) - 1, 0), len(models) + 1]))
            vectors = probability_vectors if option["type"] == "number[]" else stochastic_matrices
            options[option["name"]] = draw(vectors(size))
        elif option["name"] == "model_params":
            options["model_params"] = {m: draw(parameter_values(m)) for m in draw(subsets(tuple(models)))}
        elif option["name"] == "filter_params":
            options["filter_params"] = draw(
                parameter_values(options.get("filter", published["filter"]["default"]))
            )
        else:
            raise AssertionError(f"option {option['name']!r} has no strategy: add one")
    bad_field = None
    if draw(st.sampled_from([False] * 15 + [True])):
        bad_field = draw(_violation(options, published))
    return options, bad_field


@st.composite
def _violation(draw: st.DrawFn, options: dict[str, Any], published: dict[str, Any]) -> str:
    """Push one number just outside its published bounds (or a model parameter outside the core's);
    return the field the refusal must name."""
    numeric = sorted(n for n, o in published.items() if o["type"] in ("number", "integer"))
    nested = [
        (model, spec)
        for model in options.get("models", published.get("models", {}).get("default")) or []
        for spec in MOTION_MODELS[model].parameters
        if spec.choices is None
    ]
    if nested and draw(st.booleans()):
        model, spec = draw(st.sampled_from(nested))
        params = dict(options.get("model_params") or {})
        params[model] = {
            **params.get(model, {}),
            spec.name: draw(_outside(spec.minimum, spec.maximum, integer=False)),
        }
        options["model_params"] = params
        return f"options.model_params.{model}.{spec.name}"
    name = draw(st.sampled_from(numeric))
    option = published[name]
    options[name] = draw(_outside(option["minimum"], option["maximum"], integer=option["type"] == "integer"))
    return f"options.{name}"


def _outside(low: float, high: float, integer: bool) -> st.SearchStrategy[float]:
    if integer:
        return st.sampled_from([int(low) - 1, int(high) + 1])
    below = [low - max(abs(low), 1.0) * f for f in (1e-6, 1.0)]
    above = [high + max(abs(high), 1.0) * f for f in (1e-6, 1.0, 1e200)]
    return st.sampled_from(below + above)


def initial_states() -> st.SearchStrategy[dict[str, float] | None]:
    """None, or every InitialStateIn field within its openapi.json bounds (exclusive minimum 0: the
    smallest positive float). Half of the states keep position and velocity near the site (within 1 km,
    50 m/s), as the service also refuses a start beyond its site radius or speed limit; their stds still
    span the whole published range."""
    wide, near = {}, {}
    for name, prop in PUBLISHED["initial_state"].items():
        low = prop.get("minimum", prop.get("exclusiveMinimum"))
        if "exclusiveMinimum" in prop:
            low = math.nextafter(low, math.inf)
        wide[name] = bounded_floats(float(low), float(prop["maximum"]))
        limit = {"x": 1000.0, "y": 1000.0, "vx": 50.0, "vy": 50.0}.get(name)
        if limit is None:
            near[name] = wide[name]
        else:
            near[name] = bounded_floats(max(float(low), -limit), min(float(prop["maximum"]), limit))
    return st.none() | st.fixed_dictionaries(near) | st.fixed_dictionaries(wide)


def cases() -> st.SearchStrategy[tuple[str, dict[str, Any], dict[str, float] | None, str | None]]:
    def of(name: str):
        return st.tuples(st.just(name), option_sets(name), initial_states()).map(
            lambda c: (c[0], c[1][0], c[2], c[1][1])
        )

    return st.deferred(lambda: st.one_of(*(of(name) for name in sorted(PUBLISHED["pipelines"]))))


# -- checks --------------------------------------------------------------------------------------
def _strict_json(text: str) -> Any:
    """The JSON body, refusing NaN, Infinity and numbers that overflow a double."""

    def reject(constant: str) -> Any:
        raise AssertionError(f"non-finite number {constant} in the answer")

    def finite(literal: str) -> float:
        value = float(literal)
        assert math.isfinite(value), f"non-finite number {literal} in the answer"
        return value

    return json.loads(text, parse_constant=reject, parse_float=finite)


def _standard_error(response: Any, codes: tuple[str, ...]) -> dict[str, Any]:
    body = _strict_json(response.text)
    assert set(body) == {"error"}, response.text
    error = body["error"]
    assert set(error) == {"code", "message", "problems"}, response.text
    assert error["code"] in codes, response.text
    assert isinstance(error["message"], str) and error["message"]
    for problem in error["problems"]:
        assert set(problem) == {"index", "field", "reason"}
    return error


def _check_case(
    client: TestClient, pipeline: str, options: dict[str, Any], initial: dict | None, bad_field: str | None
) -> None:
    """Open a session with ``options`` and ``initial``, send the pipeline's normal batch, check the answers."""
    vehicle = f"fuzz-{next(_vehicle_numbers)}"
    body: dict[str, Any] = {"vehicle_id": vehicle, "pipeline": pipeline, "options": options}
    if initial is not None:
        body["initial_state"] = initial
    created = client.post("/v1/sessions", json=body, headers=ADMIN)
    assert created.status_code < 500, created.text
    event(f"{pipeline}: create {created.status_code}")
    if bad_field is not None:
        error = _standard_error(created, ("invalid_request",))
        assert created.status_code == 422
        fields = [p["field"] for p in error["problems"]]
        # The bad value is named, unless an earlier check of the same request already refused it.
        assert bad_field in fields or not all(f.startswith(bad_field.rsplit(".", 1)[0]) for f in fields), (
            fields
        )
        return
    if created.status_code != 201:
        assert created.status_code == 422, created.text
        _standard_error(created, ("invalid_request",))
        return
    session = _strict_json(created.text)
    auth = {"Authorization": f"Bearer {session['token']}"}
    url = f"/v1/sessions/{session['session_id']}"
    answer = client.post(
        f"{url}/batches",
        json={"seq": 1, "measurements": BATCHES[pipeline], "include_state": True},
        headers=auth,
    )
    assert answer.status_code < 500, answer.text
    event(f"{pipeline}: batch {answer.status_code}")
    if answer.status_code == 200:
        fixes = _strict_json(answer.text)["fixes"]
        event(f"{pipeline}: last fix {fixes[-1]['status']}")
        return
    assert answer.status_code == 422, answer.text
    error = _standard_error(answer, ("estimation_failed", "invalid_request"))
    if error["code"] == "invalid_request":
        # Options near the CPU budget: creation checks that one epoch fits (EDGEPOS_BATCH_CPU_BUDGET_MS), a
        # batch of several such epochs may not, and is refused as too costly; nothing else may refuse it.
        assert "too costly" in error["message"], answer.text
    event(f"{pipeline}: {error['code']}: {error['message']}")
    after = client.get(url, headers=auth)
    assert after.status_code == 200, after.text
    summary = _strict_json(after.text)
    assert (
        summary["last_seq"],
        summary["batches"],
        summary["epochs"],
        summary["t"],
        summary["last_fix"],
    ) == (
        0,
        0,
        0,
        None,
        None,
    ), "a failed batch changed the session"


@settings(
    max_examples=EXAMPLES,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(case=cases())
# The 500s: noise options without an upper bound overflowed their squares on the first batch ...
@example(case=("v2x_federated", {"gyro_std": 1e200}, None, "options.gyro_std"))
@example(case=("v2x_federated", {"range_std": 1e308}, None, "options.range_std"))
@example(case=("v2x_federated", {"odometer_std": 1e308}, None, "options.odometer_std"))
@example(case=("v2v_coop", {"gps_std": 1e200}, None, "options.gps_std"))
@example(
    case=(
        "rsu_imu",
        {"model_params": {"singer": {"sigma": 1e200}}},
        None,
        "options.model_params.singer.sigma",
    )
)
# ... and every model with a loose initial position: the turn-rate models' probabilities underflowed to
# exactly 0 and their weighted yaw rate was 0/0.
@example(
    case=(
        "rsu_imu",
        {"models": ["cv", "ca", "ct", "at", "singer", "current_statistical"], "priority": []},
        {"x": 0.0, "y": 0.0, "vx": 0.0, "vy": 0.0, "position_std": 1e4, "velocity_std": 1.0},
        None,
    )
)
# Found by this test: no models and no initial probabilities took the minimum of an empty list (a 500);
# an initial std whose square is 0 made every pipeline's covariance singular (now refused by the schema).
@example(case=("rsu_imu", {"models": [], "initial_probabilities": []}, None, None))
@example(
    case=(
        "v2x_federated",
        {},
        {"x": 0.0, "y": 0.0, "vx": 0.0, "vy": 0.0, "position_std": 5e-324, "velocity_std": 1.0},
        "initial_state.position_std",
    )
)
def test_no_option_set_gets_a_5xx_or_a_non_finite_number(fuzz_client, case):
    pipeline, options, initial, bad_field = case
    _check_case(fuzz_client, pipeline, options, initial, bad_field)


def test_every_numeric_option_publishes_both_bounds(fuzz_client):
    """The fuzzing above is only as wide as the published bounds: every number has both."""
    assert set(PUBLISHED["pipelines"]) == set(BATCHES)
    unbounded = [
        f"{name}.{option['name']}"
        for name, pipeline in PUBLISHED["pipelines"].items()
        for option in pipeline["options"]
        if option["type"] in ("number", "integer", "number[]", "matrix")
        and (option["minimum"] is None or option["maximum"] is None)
    ]
    assert unbounded == []
    for name, prop in PUBLISHED["initial_state"].items():
        assert "maximum" in prop and ("minimum" in prop or "exclusiveMinimum" in prop), name
