"""The direct routes' valid requests taken straight from the service's middleware to their handlers.

Nearly every request a worker serves is a batch. FastAPI would take it through its exception middleware,
its router (every included router in turn), the route, and the request-response wrapper with its two exit
stacks before the route's handler runs: about a tenth of the event loop's CPU for a 20-epoch batch.
:class:`DirectPathMiddleware`, the innermost of the service's middlewares (inside the request context,
admission, CORS and body limit), takes a request that a direct route (``one_pass_body.direct_route``)
matches in full, sent as ``application/json`` with a body that validates in one pass, and calls the route's
direct handler itself, which calls the route's dependencies in FastAPI's order. An exception the handler
raises goes to the app's handler for it, as FastAPI's exception middleware would send it. Everything else
(another path or method, another content type, a body that does not validate, dependency overrides set on
the app) goes on to FastAPI, which words every refusal; ``tests/api/test_api_direct_route.py`` holds the two
paths to the same answers.

The routes are matched as the router matches them (Starlette's ``Route.matches`` on the route itself), and
a direct route must come first in the app's routing order, so that no other route could have taken the
request (``api.app`` includes the batch router first).
"""

from __future__ import annotations

import inspect
from collections.abc import Mapping, Sequence
from typing import Any

from fastapi import FastAPI, Request, Response
from fastapi.routing import APIRoute
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException
from starlette.routing import Match

from edgepos.api.middleware import ASGIApp, Receive, Scope, Send, replaying
from edgepos.api.one_pass_body import DirectHandler, direct_handler, one_pass_model

ExceptionHandler = Any
"""An app's exception handler: ``(request, exception) -> response``, a coroutine function or a plain one."""


class DirectPathMiddleware:
    """Serve the direct routes' valid JSON requests without FastAPI's routing (see the module's docstring)."""

    def __init__(self, app: ASGIApp, fastapi_app: FastAPI, routes: Sequence[APIRoute]) -> None:
        self.app = app
        self.fastapi_app = fastapi_app
        self.routes: list[tuple[APIRoute, DirectHandler, Any]] = []
        for route in routes:
            handler, model = direct_handler(route), one_pass_model(route)
            if handler is None or model is None:
                raise TypeError(f"{route.path}: not a direct route")
            self.routes.append((route, handler, model))
        # As Starlette splits them: the 500 handler is the server-error middleware's, the rest are the
        # exception middleware's, by status code (for HTTP exceptions) or by exception class.
        handlers: Mapping[Any, ExceptionHandler] = fastapi_app.exception_handlers
        self.status_handlers = {
            key: value for key, value in handlers.items() if isinstance(key, int) and key != 500
        }
        self.class_handlers = {
            key: value for key, value in handlers.items() if isinstance(key, type) and key is not Exception
        }

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] != "POST" or self.fastapi_app.dependency_overrides:
            await self.app(scope, receive, send)
            return
        for route, handler, model in self.routes:
            match, child_scope = route.matches(scope)
            if match is Match.FULL:
                break
        else:
            await self.app(scope, receive, send)
            return
        # The first content-type header, as Starlette's ``request.headers.get`` reads it (names are lower case).
        content_type = next((value for name, value in scope["headers"] if name == b"content-type"), None)
        if content_type != b"application/json":
            await self.app(scope, receive, send)
            return
        message = await receive()
        body = message.get("body", b"") if message["type"] == "http.request" else None
        if body is None or message.get("more_body", False):  # a streamed body or a client gone: FastAPI's
            await self.app(scope, replaying(message, receive), send)
            return
        try:
            validated = model.model_validate_json(body)
        except ValueError:  # pydantic's ValidationError included: FastAPI words the refusal
            await self.app(scope, replaying(message, receive), send)
            return
        scope.update(child_scope)  # path_params, endpoint and route, as the router sets them
        scope["router"] = self.fastapi_app.router
        replay = replaying(message, receive)
        request = Request(scope, replay, send)
        try:
            response = await handler(request, validated)
        except Exception as error:  # noqa: BLE001 - to the app's handler for it, or re-raised unhandled
            response = await self._handled(request, error)
        await response(scope, replay, send)

    async def _handled(self, request: Request, error: Exception) -> Response:
        """The app's answer to ``error`` (its handler by status code, then by class); re-raised unhandled."""
        handler: ExceptionHandler | None = None
        if isinstance(error, HTTPException):
            handler = self.status_handlers.get(error.status_code)
        if handler is None:
            handler = next(
                (self.class_handlers[cls] for cls in type(error).__mro__ if cls in self.class_handlers), None
            )
        if handler is None:
            raise error
        if inspect.iscoroutinefunction(handler):
            response: Response = await handler(request, error)
        else:
            response = await run_in_threadpool(handler, request, error)
        return response
