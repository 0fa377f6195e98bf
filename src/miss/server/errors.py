"""Server errors and the handlers that turn every expected failure into a 4xx JSON answer.

Engine errors (``MissError``) carry messages that already name the fix; the server only
picks the status code. Nothing a client sends should produce a 500 with a traceback.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from miss.errors import MissError, UnreadableVolume, UnsupportedFormat
from miss.server.logmask import mask

log = logging.getLogger("miss.server")


class NotFound(MissError, LookupError):
    """An id that names no volume or model (or a slice outside the volume)."""


class UploadTooLarge(MissError, ValueError):
    """An upload, or the files a zip expands to, over the configured limit."""


class UnsafeArchive(UnreadableVolume):
    """A zip with members that would land outside its folder (``../``, absolute, links)."""


class NotReady(MissError, RuntimeError):
    """A model file asked for before its job is done."""


class Unauthorized(MissError, PermissionError):
    """No credentials, or ones that name no live session (log in again)."""


class Forbidden(MissError, PermissionError):
    """Credentials that are valid but not enough: a missing CSRF token, a non-admin."""


class Gone(MissError, LookupError):
    """A share link that has expired or was revoked."""


class TooManyRequests(MissError, RuntimeError):
    """A client over its rate limit (failed logins)."""


#: Most specific first; anything else from the engine is a bad request body (422).
STATUS: tuple[tuple[type[MissError], int], ...] = (
    (NotFound, 404),
    (Unauthorized, 401),
    (Forbidden, 403),
    (Gone, 410),
    (TooManyRequests, 429),
    (UploadTooLarge, 413),
    (UnsupportedFormat, 415),
    (NotReady, 409),
)


def status_of(exc: MissError) -> int:
    for cls, code in STATUS:
        if isinstance(exc, cls):
            return code
    return 422


async def miss_error_handler(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, MissError)
    code = status_of(exc)
    if code not in (401, 404, 410):  # the everyday ones would drown the log
        # An upload's error may quote names from inside it (a folder called after the
        # patient): the client gets the message, the log only the kind of error.
        upload = request.method == "POST" and request.url.path == "/api/volumes"
        said = type(exc).__name__ if upload else str(exc)
        log.info("%s %s -> %d: %s", request.method, mask(request.url.path), code, said)
    headers = {"WWW-Authenticate": 'Bearer realm="miss"'} if code == 401 else None
    return JSONResponse({"detail": str(exc)}, status_code=code, headers=headers)


async def validation_handler(request: Request, exc: Exception) -> JSONResponse:
    """FastAPI's 422, with ``detail`` as one readable sentence and the list kept as ``errors``."""
    assert isinstance(exc, RequestValidationError)
    parts = []
    for err in exc.errors():
        where = ".".join(str(p) for p in err.get("loc", ()) if p not in ("body", "query", "path"))
        parts.append(f"{where}: {err.get('msg', 'invalid')}" if where else str(err.get("msg")))
    detail = "; ".join(parts) or "invalid request"
    errors = [
        {"loc": list(e.get("loc", ())), "msg": e.get("msg"), "type": e.get("type")}
        for e in exc.errors()
    ]
    return JSONResponse({"detail": detail, "errors": errors}, status_code=422)


def install(app: FastAPI) -> None:
    app.add_exception_handler(MissError, miss_error_handler)
    app.add_exception_handler(RequestValidationError, validation_handler)
