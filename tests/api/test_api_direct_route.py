"""The batch route's direct handler (``one_pass_body.direct_route``), which ``api.direct_path`` calls: a valid
JSON batch skips FastAPI's routing and dependency solving, and every request answers exactly as FastAPI's own
handler answers it."""

from __future__ import annotations

import json
from typing import Any

import pytest
from apihelp import ADMIN, batch_body, bearer, open_session
from edgepos.api import session_service
from edgepos.api.one_pass_body import dependency_calls, direct_route
from edgepos.api.routes import json_body, sessions
from fastapi import APIRouter, Depends, Request, Response, routing
from starlette.middleware.exceptions import ExceptionMiddleware


def test_a_valid_batch_is_answered_without_fastapis_dependency_solving(client, monkeypatch) -> None:
    session_id, token = open_session(client)

    async def refuse(*_args: Any, **_kwargs: Any) -> Any:
        raise AssertionError("the batch took FastAPI's dependency solving")

    monkeypatch.setattr(routing, "solve_dependencies", refuse)
    response = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 5), headers=token)
    assert response.status_code == 200, response.text
    assert len(response.json()["fixes"]) == 5


def test_a_valid_batch_is_answered_before_fastapis_routing(client, monkeypatch) -> None:
    session_id, token = open_session(client)
    client.get("/healthz")  # the middleware stack is built: the refusal below applies to its instances

    async def refuse(*_args: Any, **_kwargs: Any) -> Any:
        raise AssertionError("the batch went through FastAPI's exception middleware and router")

    monkeypatch.setattr(ExceptionMiddleware, "__call__", refuse)
    response = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 5), headers=token)
    assert response.status_code == 200, response.text
    assert response.headers["x-request-id"]
    assert client.get("/healthz").status_code == 500  # the refusal is in place for what FastAPI routes


def test_an_exception_no_handler_takes_is_the_generic_500_on_either_path(client, monkeypatch) -> None:
    async def fail(*_args: Any, **_kwargs: Any) -> Any:
        raise RuntimeError("a bug")

    monkeypatch.setattr(session_service, "apply_batch", fail)
    answers = []
    for overridden in (False, True):
        if overridden:
            client.app.dependency_overrides[json_body] = json_body  # FastAPI's handler
        session_id, token = open_session(client, vehicle_id=f"car-bug-{overridden}")
        response = client.post(f"/v1/sessions/{session_id}/batches", json=batch_body(1, 0, 2), headers=token)
        answers.append((response.status_code, response.json()["error"]["code"]))
    assert answers == [(500, "internal_error"), (500, "internal_error")]


def _requests(session_id: str, token: dict[str, str], other_token: dict[str, str]) -> list[dict[str, Any]]:
    """A session's life on the batch route: applied, replayed, refused for every reason a check gives."""
    path = f"/v1/sessions/{session_id}/batches"
    valid = json.dumps(batch_body(1, 0, 3)).encode()
    json_type = {"content-type": "application/json"}
    return [
        {"url": path, "content": valid, "headers": {**token, **json_type}},
        {"url": path, "content": valid, "headers": {**token, **json_type}},  # the replay
        {"url": path, "content": json.dumps(batch_body(1, 3, 2)).encode(), "headers": {**token, **json_type}},
        {"url": path, "content": json.dumps(batch_body(5, 3, 2)).encode(), "headers": {**token, **json_type}},
        {"url": path, "content": json.dumps(batch_body(2, 3, 2)).encode(), "headers": {**ADMIN, **json_type}},
        {"url": path, "content": json.dumps(batch_body(3, 5, 2)).encode(), "headers": json_type},
        {"url": path, "content": valid, "headers": {"authorization": "Basic abc", **json_type}},
        {"url": path, "content": valid, "headers": {**other_token, **json_type}},
        {"url": path, "content": valid, "headers": {**bearer(f"{session_id}.wrong"), **json_type}},
        {"url": path, "content": valid, "headers": {**token, "content-type": "text/plain"}},
        {"url": path, "content": valid, "headers": token},
        {
            "url": path,
            "content": json.dumps(batch_body(3, 5, 2)).encode(),
            "headers": {**token, "content-type": "application/json; charset=utf-8"},
        },
        {"url": path, "content": b'{"seq": 4, "measurements": []}', "headers": {**token, **json_type}},
        {"url": path, "content": b'{"seq": 4, "measurements": [', "headers": {**token, **json_type}},
        {"url": "/v1/sessions/nobody/batches", "content": valid, "headers": {**ADMIN, **json_type}},
    ]


def _answers(client: Any, vehicle: str) -> list[tuple[int, dict[str, str], str]]:
    session_id, token = open_session(client, vehicle_id=vehicle)
    _other_id, other_token = open_session(client, vehicle_id=f"{vehicle}-other")
    answers = []
    for request in _requests(session_id, token, other_token):
        response = client.post(**request)
        headers = {k: v for k, v in response.headers.items() if k != "x-request-id"}
        answers.append((response.status_code, headers, response.text.replace(session_id, "<session>")))
    return answers


def test_every_request_answers_as_fastapis_own_handler_answers_it(client) -> None:
    direct = _answers(client, "car-direct")
    client.app.dependency_overrides[json_body] = (
        json_body  # any override: FastAPI's handler, which honours it
    )
    usual = _answers(client, "car-usual")
    assert [status for status, _, _ in direct] == [
        200,
        200,
        409,
        409,
        200,
        401,
        401,
        403,
        401,
        415,
        415,
        200,
        422,
        422,
        404,
    ]
    assert direct == usual


def test_a_route_whose_dependencies_are_not_its_direct_handlers_is_refused() -> None:
    async def handler(request: Request, body: Any) -> Response:
        return Response()

    async def check(request: Request) -> None:
        return None

    async def endpoint(session_id: str, body: sessions.BatchIn) -> Response:
        return Response()

    router = APIRouter()
    route_class = direct_route(handler, (json_body,))
    with pytest.raises(TypeError, match="does not match"):
        router.add_api_route(
            "/{session_id}",
            endpoint,
            methods=["POST"],
            dependencies=[Depends(json_body), Depends(check)],
            route_class_override=route_class,
        )
    router.add_api_route(
        "/{session_id}",
        endpoint,
        methods=["POST"],
        dependencies=[Depends(json_body)],
        route_class_override=route_class,
    )
    assert dependency_calls(router.routes[-1].dependant) == (json_body,)
