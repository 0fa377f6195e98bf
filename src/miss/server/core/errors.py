"""Server errors and the handlers that turn every expected failure into a 4xx JSON answer.

Engine errors (``MissError``) carry messages that already name the fix; the server only
picks the status code. Nothing a client sends should produce a 500 with a traceback.
"""

from __future__ import annotations

import json
import logging
import reprlib
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from python_multipart.exceptions import FormParserError
from starlette.exceptions import HTTPException

from miss.errors import (
    DiskFull,
    InputTooLarge,
    MissError,
    PacsError,
    PacsTimeout,
    UnsupportedFormat,
    WrongStudy,
)
from miss.server.core.logmask import mask

log = logging.getLogger("miss.server")


class NotFound(MissError, LookupError):
    """An id that names no volume or model (or a slice outside the volume)."""


#: An upload, or the files a zip expands to, over the configured limit (413).
UploadTooLarge = InputTooLarge


class BodyTooLarge(MissError, ValueError):
    """A JSON request body over the few kilobytes any request of the API needs."""


class NotReady(MissError, RuntimeError):
    """A model file asked for before its job is done."""


class Conflict(MissError, RuntimeError):
    """A request the state of what it names refuses until someone acts (409): a scan
    flagged for burned-in text offered to guests before its owner confirmed it."""


class Unauthorized(MissError, PermissionError):
    """No credentials, or ones that name no live session (log in again)."""


class Forbidden(MissError, PermissionError):
    """Credentials that are valid but not enough: a missing CSRF token, a non-admin."""


class Gone(MissError, LookupError):
    """A share link that has expired or was revoked."""


class UploadTooSlow(MissError, TimeoutError):
    """An upload whose body stopped arriving, or arrives slower than the minimum rate (408)."""


class TooManyRequests(MissError, RuntimeError):
    """A client over its rate limit (failed logins)."""


class ChooseSeries(MissError, ValueError):
    """An upload that holds several DICOM series and names none (409): ``series`` lists
    them (uid, description, modality, slices, dims) for the client to pick one and send
    the upload again with its ``uid`` in the form field ``series``."""

    def __init__(self, message: str, series: list[dict[str, Any]]) -> None:
        super().__init__(message)
        self.series = series


def answer_fields(exc: MissError) -> dict[str, Any]:
    """What an error's JSON answer holds beside ``detail``: the series to choose among
    (:class:`ChooseSeries`), the technical detail behind a plain sentence (``technical``,
    set by the upload route)."""
    fields: dict[str, Any] = {}
    if isinstance(exc, ChooseSeries):
        fields["series"] = exc.series
    technical = getattr(exc, "technical", "")
    if isinstance(technical, str) and technical:
        fields["technical"] = technical
    return fields


#: Most specific first; anything else from the engine is a bad request body (422).
STATUS: tuple[tuple[type[MissError], int], ...] = (
    (NotFound, 404),
    (Unauthorized, 401),
    (Forbidden, 403),
    (Gone, 410),
    (TooManyRequests, 429),
    (UploadTooSlow, 408),
    (UploadTooLarge, 413),
    (BodyTooLarge, 413),
    (UnsupportedFormat, 415),
    (NotReady, 409),
    (Conflict, 409),
    (ChooseSeries, 409),
    (WrongStudy, 409),
    (DiskFull, 507),
    (PacsTimeout, 504),
    (PacsError, 502),
)


def status_of(exc: MissError) -> int:
    """The HTTP status of a MissError: the first match in ``STATUS``, else 422."""
    for cls, code in STATUS:
        if isinstance(exc, cls):
            return code
    return 422


async def miss_error_handler(request: Request, exc: Exception) -> JSONResponse:
    """Answer a MissError with its status and a JSON ``detail`` (401 with a
    ``WWW-Authenticate`` challenge); logs all but the everyday 401, 404 and 410."""
    assert isinstance(exc, MissError)
    code = status_of(exc)
    if code not in (401, 404, 410):  # the everyday ones would drown the log
        # An upload's error may quote names from inside it (a folder called after the
        # patient): the client gets the message, the log only the kind of error.
        upload = request.method == "POST" and request.url.path == "/api/volumes"
        said = type(exc).__name__ if upload else str(exc)
        log.info("%s %s -> %d: %s", request.method, mask(request.url.path), code, said)
    headers = {"WWW-Authenticate": 'Bearer realm="miss"'} if code == 401 else None
    body = {"detail": str(exc), **answer_fields(exc)}
    return JSONResponse(body, status_code=code, headers=headers)


async def validation_handler(request: Request, exc: Exception) -> JSONResponse:
    """FastAPI's 422, with ``detail`` as readable sentences (which field, what it should
    be, what came) and the raw list kept as ``errors``."""
    assert isinstance(exc, RequestValidationError)
    found = list(exc.errors())
    detail = "; ".join(_explain(found, request)) or "the request is not valid; see /docs."
    errors = [
        {"loc": list(e.get("loc", ())), "msg": e.get("msg"), "type": e.get("type")} for e in found
    ]
    return JSONResponse({"detail": detail, "errors": errors}, status_code=422)


#: What a value should be, by pydantic error type (and union branch tag).
_EXPECTED = {
    "int_type": "a whole number",
    "int_parsing": "a whole number",
    "int_from_float": "a whole number",
    "float_type": "a number",
    "float_parsing": "a number",
    "finite_number": "a finite number (not NaN or Infinity)",
    "string_type": "a string",
    "bool_type": "true or false",
    "bool_parsing": "true or false",
    "list_type": "a list",
    "dict_type": "an object",
    "model_type": "an object",
    "model_attributes_type": "an object",
    "int": "a whole number",
    "float": "a number",
    "str": "a string",
    "bool": "true or false",
    "list[int]": "a list of whole numbers",
    "list[float]": "a list of numbers",
}
_SOURCES = ("body", "query", "path", "header", "cookie")
_JSON_TYPES = ("application/json",)


def _is_branch(part: object) -> bool:
    """A union member's tag in a location (``int``, ``list[int]``), not a field name."""
    return isinstance(part, str) and (part in _EXPECTED or "[" in part or "-" in part)


def _where(loc: tuple[Any, ...]) -> tuple[str, str]:
    """(source, field path) of an error location: ``("body", "levels[2]")``."""
    source = loc[0] if loc and loc[0] in _SOURCES else ""
    rest = loc[1:] if source else loc
    path = ""
    for i, part in enumerate(rest):
        if isinstance(part, int):
            path += f"[{part}]"
        elif not (i > 0 and _is_branch(part)):
            path += f".{part}" if path else str(part)
    return str(source), path


def _shown(value: Any) -> str:
    """A short JSON rendering of what the client sent."""
    try:
        text = json.dumps(value, allow_nan=True, default=str)
    except (TypeError, ValueError, RecursionError):  # deep lists parse but do not encode
        text = reprlib.repr(value)  # depth-limited, unlike repr
    return text if len(text) <= 60 else text[:57] + "..."


def _explain(found: list[Any], request: Request) -> list[str]:
    """One sentence per field; the members of a union (``sample_rate``: n or [x, y, z])
    are merged into one "should be A or B"."""
    groups: dict[tuple[str, str], list[Any]] = {}
    for err in found:
        loc = tuple(err.get("loc", ()))
        source, path = _where(loc)
        top = path.split(".")[0].split("[")[0] if any(_is_branch(p) for p in loc[2:]) else path
        groups.setdefault((source, top), []).append(err)
    return [_sentence(source, field, errs, request) for (source, field), errs in groups.items()]


def _sentence(source: str, field: str, errs: list[Any], request: Request) -> str:
    err = errs[0]
    kind, ctx = err.get("type", ""), err.get("ctx") or {}
    if source == "body" and (not field or kind == "json_invalid"):
        return _body_sentence(kind, err, ctx, request)
    name = f"{field!r}" + (f" ({source} parameter)" if source in ("query", "path") else "")
    if kind == "missing":
        return f"{name} is required"
    if kind == "extra_forbidden":
        return f"{name} is not a field of this request; remove it (see /docs for the fields)"
    got = _shown(min(errs, key=lambda e: len(e.get("loc", ()))).get("input"))
    if "password" in field or "token" in field:  # never echoed, not even to its sender
        got = "(not shown)"
    if len(errs) > 1:  # a union: name each alternative once
        tags = [next((p for p in e.get("loc", ())[2:] if _is_branch(p)), "") for e in errs]
        ways = list(dict.fromkeys(_EXPECTED.get(t, t) for t in tags if t))
        if ways:
            return f"{name} should be {' or '.join(ways)}, got {got}"
    if kind in _EXPECTED:
        return f"{name} should be {_EXPECTED[kind]}, got {got}"
    msg = str(err.get("msg", "is not valid"))
    said = msg.replace("Input should", "should", 1) if msg.startswith("Input should") else msg
    return f"{name} {said[0].lower() + said[1:]}, got {got}"


def _body_sentence(kind: str, err: Any, ctx: dict[str, Any], request: Request) -> str:
    """The body as a whole: missing, not JSON, or JSON that is no object."""
    sent = request.headers.get("content-type", "").split(";")[0].strip().lower()
    hint = "send a JSON object ({...}) with Content-Type: application/json (see /docs)"
    if kind == "json_invalid":
        at = err.get("loc", ("body", 0))[-1]
        why = ctx.get("error", "decode error")
        return f"the request body is not valid JSON ({why} at character {at}); {hint}"
    if kind == "missing":
        return f"the request body is empty; {hint}"
    if sent not in _JSON_TYPES and not sent.endswith("+json"):
        return f"the request body is not JSON (Content-Type: {sent or 'none'}); {hint}"
    got = err.get("input")
    what = {list: "a list", str: "a string", bool: "true or false", type(None): "null"}.get(
        type(got), "a number" if isinstance(got, int | float) else _shown(got)
    )
    return f"the request body must be a JSON object, got {what}; {hint}"


async def multipart_handler(request: Request, exc: Exception) -> JSONResponse:
    """A multipart body that does not parse (no boundary where one should be, headers
    too long): the client's mistake, a 400 that says so."""
    log.info("%s %s -> 400: malformed multipart", request.method, mask(request.url.path))
    return JSONResponse(
        {
            "detail": f"the multipart/form-data body is malformed ({exc}); send the file as "
            "a form upload in the field 'file' (e.g. curl -F file=@series.zip)."
        },
        status_code=400,
    )


#: Starlette's and FastAPI's own short answers, said with what to do.
_HTTP_DETAILS = {
    (400, "There was an error parsing the body"): "the request body could not be parsed as "
    "JSON (malformed, or nested too deeply); send a JSON object with "
    "Content-Type: application/json (see /docs).",
    (404, "Not Found"): "no such page or API route: {method} {path}; see /docs for the API.",
    (405, "Method Not Allowed"): "{method} is not allowed on {path}; see /docs for the methods.",
}


async def http_error_handler(request: Request, exc: Exception) -> Response:
    """Starlette's HTTP errors (unknown route, wrong method, unparsable body) as JSON
    with a ``detail`` that says what to do; anything else unchanged."""
    assert isinstance(exc, HTTPException)
    text = _HTTP_DETAILS.get((exc.status_code, str(exc.detail)))
    if text is not None:
        detail = text.format(method=request.method, path=mask(request.url.path))
        exc = HTTPException(exc.status_code, detail, exc.headers)
    return await http_exception_handler(request, exc)


def install(app: FastAPI) -> None:
    """Register the handlers that turn errors into JSON answers with a ``detail``."""
    app.add_exception_handler(MissError, miss_error_handler)
    app.add_exception_handler(RequestValidationError, validation_handler)
    app.add_exception_handler(FormParserError, multipart_handler)
    app.add_exception_handler(HTTPException, http_error_handler)
