"""Errors of the location adapter as RFC 7807 problem details (``application/problem+json``).

ETSI GS MEC 013 answers every error with a ProblemDetails body, so a MEC client's error handling works
unchanged; the rest of the service keeps its own body (``{"error": {"code", "message", "problems"}}``),
whose machine code and per-field problem list its clients rely on. The same refusal (status, sentence,
the fields and why) is written in either shape; here the fields' reasons end ``detail``.
"""

from __future__ import annotations

from collections.abc import Sequence
from http import HTTPStatus

from edgepos.api.location.schemas import ProblemDetails
from edgepos.api.schemas import ProblemModel

PREFIX = "/location/"
MEDIA_TYPE = "application/problem+json"


def is_location_path(path: str) -> bool:
    return path.startswith(PREFIX)


def problem_body(status: int, message: str, problems: Sequence[ProblemModel], instance: str) -> bytes:
    detail = message
    extra = [f"{problem.field}: {problem.reason}" for problem in problems if problem.reason not in message]
    if extra:
        detail += " (" + "; ".join(extra) + ")"
    try:
        title = HTTPStatus(status).phrase
    except ValueError:
        title = "Error"
    body = ProblemDetails(type="about:blank", title=title, status=status, detail=detail, instance=instance)
    return body.model_dump_json().encode()
