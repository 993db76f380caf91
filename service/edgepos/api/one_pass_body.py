"""Request bodies validated in one pass from their bytes, for the routes that carry the most of them.

FastAPI decodes a JSON body with the standard library into dicts and lists, then validates those against
the body's model: two passes over every measurement of a batch. pydantic validates the model straight from
the bytes in one pass (``model_validate_json``) for about 60 % of that cost, measured on a 20-epoch RSU
batch. :class:`OnePassBodyRoute` does that first; FastAPI then receives the model instance, which it passes
through unvalidated (pydantic does not revalidate instances). A body that does not validate in one pass
takes FastAPI's usual path instead (``json.loads``, then its validation), so every refusal (its status,
problems and their wording) is exactly what it was; the two validations agree on what they accept
(``tests/api/test_api_one_pass_body.py`` holds them to it on generated bodies).

:func:`direct_route` goes one step further for the busiest route, the batch: it gives the route a direct
handler, a function that calls the route's dependencies itself, in the order FastAPI solves them, and then
the endpoint, without FastAPI's dependency solving per request. ``api.direct_path`` hands it the requests
sent as ``application/json`` whose body validates in one pass, before FastAPI's routing; anything else
takes the route's handler as above.
"""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

from fastapi import Request, Response
from fastapi.dependencies.models import Dependant
from fastapi.routing import APIRoute
from pydantic import BaseModel


class _OnePassRequest(Request):
    """A request whose ``json()`` is its body's model when the bytes validate in one pass."""

    def __init__(self, request: Request, model: type[BaseModel]) -> None:
        super().__init__(request.scope, request.receive, request._send)  # send: private in Starlette
        self._body_model = model

    async def json(self) -> Any:
        if not hasattr(self, "_json"):
            body = await self.body()
            try:
                self._json = self._body_model.model_validate_json(body)
            except ValueError:  # pydantic's ValidationError included: the usual path decides and words it
                self._json = usual_decoding(body)
        return self._json


def usual_decoding(body: bytes) -> Any:
    """Starlette's own decoding of a JSON body, for the bodies the one pass does not take."""
    return json.loads(body)


def one_pass_model(route: APIRoute) -> type[BaseModel] | None:
    """The pydantic model of a route's whole JSON body (one parameter, not embedded), else None."""
    field = route.body_field
    # _embed_body_fields: FastAPI's own flag for an embedded body (no public accessor)
    if field is None or route._embed_body_fields or len(route.dependant.body_params) != 1:
        return None
    annotation = field.field_info.annotation
    return annotation if isinstance(annotation, type) and issubclass(annotation, BaseModel) else None


class OnePassBodyRoute(APIRoute):
    """An APIRoute whose model body is validated from the request's bytes in one pass when it can be."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        model = one_pass_model(self)
        if model is None:
            return handler

        async def one_pass(request: Request) -> Response:
            return await handler(_OnePassRequest(request, model))

        return one_pass


DirectHandler = Callable[[Request, Any], Awaitable[Response]]
"""A route's endpoint with its dependencies called in FastAPI's order: (request, the validated body) -> response."""


def dependency_calls(dependant: Dependant) -> tuple[Callable[..., Any], ...]:
    """The calls of a route's dependencies in the order FastAPI solves them: each one's own first, then it."""
    calls: list[Callable[..., Any]] = []
    for sub in dependant.dependencies:
        calls.extend(dependency_calls(sub))
        if sub.call is not None:
            calls.append(sub.call)
    return tuple(calls)


def direct_route(handler: DirectHandler, dependencies: tuple[Callable[..., Any], ...]) -> type[APIRoute]:
    """A one-pass route class with ``handler`` as its direct handler (see the module's docstring).

    ``dependencies`` are the calls ``handler`` makes, in :func:`dependency_calls`' order: a route whose
    declared dependencies are not these is refused when it is built, so that the handler cannot skip one
    the route gained."""

    class DirectRoute(OnePassBodyRoute):
        direct_handler = staticmethod(handler)

        def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
            if one_pass_model(self) is None or dependency_calls(self.dependant) != dependencies:
                raise TypeError(f"{self.path}: its direct handler does not match its body or dependencies")
            return super().get_route_handler()

    return DirectRoute


def direct_handler(route: APIRoute) -> DirectHandler | None:
    """The direct handler of a route made by :func:`direct_route`, else None."""
    handler: DirectHandler | None = getattr(route, "direct_handler", None)
    return handler
