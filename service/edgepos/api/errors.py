"""One error body for every failure: ``{"error": {"code", "message", "problems": [...]}}``.

Routes raise :class:`ApiError`; FastAPI's validation errors and Starlette's HTTP errors (unknown
route, wrong method) are mapped to the same shape. Anything else is a bug: the outermost middleware
logs it with its traceback and answers a generic 500 that reveals nothing.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping, Sequence
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import Response
from starlette.exceptions import HTTPException as StarletteHTTPException

from edgepos.api.location import problems as location_problems
from edgepos.api.measurement_schemas import MEASUREMENT_TYPES
from edgepos.api.schemas import ErrorBody, ErrorDetail, ProblemModel
from edgepos.pipelines.base import Problem
from edgepos.store.base import NotReplicated, StoreUnavailable

logger = logging.getLogger("edgepos.api")

STATUS_OF_CODE: dict[str, int] = {
    "invalid_request": 422,
    "unauthorized": 401,
    "forbidden": 403,
    "not_found": 404,
    "method_not_allowed": 405,
    "conflict": 409,
    "superseded": 409,
    "payload_too_large": 413,
    "unsupported_media_type": 415,
    "too_many_sessions": 429,
    "rate_limited": 429,
    "estimation_failed": 422,
    "unavailable": 503,
    "internal_error": 500,
}


class ApiError(Exception):
    """A refusal with its machine code, a sentence for humans and the problems found."""

    def __init__(
        self,
        code: str,
        message: str,
        problems: Iterable[ProblemModel] = (),
        headers: dict[str, str] | None = None,
    ) -> None:
        super().__init__(message)
        self.code = code
        self.status = STATUS_OF_CODE[code]
        self.message = message
        self.problems = list(problems)
        self.headers = headers or {}


def error_body(code: str, message: str, problems: Sequence[ProblemModel] = ()) -> bytes:
    """The serialised error body."""
    detail = ErrorDetail(code=code, message=message, problems=list(problems))
    return ErrorBody(error=detail).model_dump_json().encode()


def error_response(error: ApiError, request: Request | None = None) -> Response:
    """The error's response; on the location adapter's paths as RFC 7807 problem details (its clients
    follow ETSI GS MEC 013, which answers errors so)."""
    headers = dict(error.headers)
    if error.status == 401:
        headers.setdefault("WWW-Authenticate", "Bearer")
    if request is not None and location_problems.is_location_path(request.url.path):
        return Response(
            location_problems.problem_body(error.status, error.message, error.problems, request.url.path),
            status_code=error.status,
            media_type=location_problems.MEDIA_TYPE,
            headers=headers,
        )
    return Response(
        error_body(error.code, error.message, error.problems),
        status_code=error.status,
        media_type="application/json",
        headers=headers,
    )


def pipeline_problems(
    problems: Iterable[Problem],
    list_name: str | None = None,
    rename: Callable[[int, str], str] | None = None,
) -> list[ProblemModel]:
    """Pipeline problems as wire problems; with ``list_name`` an indexed field becomes
    ``list_name[index].field`` so it names the request's own path (``rename`` maps an observation's
    field to the wire's name for that item, e.g. pseudorange -> pseudorange_m)."""
    out = []
    for problem in problems:
        field = problem.field
        if list_name is not None and problem.index is not None:
            if rename is not None:
                field = rename(problem.index, field)
            field = f"{list_name}[{problem.index}].{field}"
        out.append(ProblemModel(index=problem.index, field=field, reason=problem.reason))
    return out


def _line_and_column(document: Any, position: int) -> tuple[int, int]:
    """1-based line and column of character ``position`` in the request body (as the JSON decoder saw it)."""
    text = document.decode("utf-8", "replace") if isinstance(document, (bytes, bytearray)) else str(document)
    before = text[: max(0, position)]
    line = before.count("\n") + 1
    return line, position - (before.rfind("\n") + 1) + 1


def validation_problems(errors: Sequence[Mapping[str, Any]], document: Any = None) -> list[ProblemModel]:
    """FastAPI/pydantic error entries as wire problems: ``loc`` becomes a dotted path with
    ``[i]`` for list items, the union tag pydantic inserts is dropped, and items of the
    ``measurements`` list carry their index. A body that is not JSON at all is named as ``body`` with
    the line and column of the syntax error (``document``: the body as the decoder read it)."""
    problems = []
    for error in errors:
        if error.get("type") == "json_invalid":
            detail = (error.get("ctx") or {}).get("error") or "syntax error"
            where = ""
            position = (error.get("loc") or (None, None))[-1]
            if document is not None and isinstance(position, int):
                line, column = _line_and_column(document, position)
                where = f" at line {line}, column {column}"
            problems.append(ProblemModel(index=None, field="body", reason=f"not valid JSON{where}: {detail}"))
            continue
        loc = list(error.get("loc", ()))
        if loc and loc[0] in ("body", "path", "query", "header"):
            loc = loc[1:]
        index = None
        if len(loc) >= 2 and loc[0] == "measurements" and isinstance(loc[1], int):
            index = loc[1]
            if len(loc) >= 3 and loc[2] in MEASUREMENT_TYPES:
                del loc[2]
            if error.get("type") in ("union_tag_invalid", "union_tag_not_found"):
                loc.append("type")
        field = ""
        for part in loc:
            if isinstance(part, int):
                field += f"[{part}]"
            else:
                field += f".{part}" if field else str(part)
        reason = str(error.get("msg", "is invalid"))
        problems.append(ProblemModel(index=index, field=field or "body", reason=reason))
    return problems


def store_unavailable_error(error: StoreUnavailable) -> ApiError:
    """503 with Retry-After for a store that does not answer. The store's own message names hosts and
    ports: it is logged, and the answer is a fixed sentence (a replication shortfall is named as is)."""
    logger.warning("store unavailable", extra={"event": "store_unavailable", "error": str(error)})
    message = (
        str(error) if isinstance(error, NotReplicated) else "the session store does not answer; retry shortly"
    )
    return ApiError("unavailable", message, headers={"Retry-After": "1"})


def invalid_request_error(errors: Sequence[Mapping[str, Any]], document: Any = None) -> ApiError:
    """422 listing every problem of a body that is not JSON or does not fit its schema (see
    :func:`validation_problems`)."""
    problems = validation_problems(errors, document)
    count = len(problems)
    message = f"the request is invalid ({count} problem{'s' if count != 1 else ''})"
    return ApiError("invalid_request", message, problems)


_STATUS_CODES = {
    404: "not_found",
    405: "method_not_allowed",
    401: "unauthorized",
    403: "forbidden",
    409: "conflict",
    413: "payload_too_large",
    415: "unsupported_media_type",
    429: "rate_limited",
    503: "unavailable",
}


def install_error_handlers(app: FastAPI) -> None:
    """Route every exception through the one error body."""

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, error: ApiError) -> Response:
        return error_response(error, request)

    @app.exception_handler(StoreUnavailable)
    async def _store_unavailable(request: Request, error: StoreUnavailable) -> Response:
        return error_response(store_unavailable_error(error), request)

    @app.exception_handler(RequestValidationError)
    async def _validation_error(request: Request, error: RequestValidationError) -> Response:
        return error_response(invalid_request_error(error.errors(), error.body), request)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, error: StarletteHTTPException) -> Response:
        if error.status_code == 400:  # FastAPI could not decode the body (e.g. not UTF-8)
            problem = ProblemModel(index=None, field="body", reason=f"cannot be read as JSON: {error.detail}")
            return error_response(
                ApiError("invalid_request", "the request body is not valid JSON", [problem]), request
            )
        code = _STATUS_CODES.get(
            error.status_code, "invalid_request" if error.status_code < 500 else "internal_error"
        )
        if error.status_code == 404:
            message = f"no such resource: {request.url.path}"
        elif error.status_code == 405:
            message = f"method {request.method} is not allowed on {request.url.path}"
        else:
            message = str(error.detail)
        refusal = ApiError(code, message)
        refusal.status = error.status_code
        response = error_response(refusal, request)
        for key, value in (error.headers or {}).items():
            response.headers[key] = value
        template = getattr(request.scope.get("route"), "path", None)
        allowed = getattr(request.app.state, "allowed_methods", {}).get(template)
        if error.status_code == 405 and allowed:
            # Starlette names only the first route of the path; list every route's methods
            response.headers["Allow"] = ", ".join(sorted(allowed))
        return response
