"""Who is asking: bearer tokens, the session cookie and its CSRF check.

Two ways to present the same session token:

- ``Authorization: Bearer TOKEN`` for scripts. Browsers never attach this header on
  their own, so such requests need no CSRF defence.
- The ``miss_session`` cookie (HttpOnly, SameSite=Lax) for the pages. A browser sends it
  with requests another site triggers, so every cookie-authenticated write must also
  carry ``X-CSRF-Token`` equal to the session's CSRF value, which the pages read from the
  ``miss_csrf`` cookie (double submit, tied to the session). A cross-site page can neither
  read that cookie nor set a custom header without a CORS preflight this server refuses.
"""

from __future__ import annotations

import hmac
from collections.abc import Mapping
from urllib.parse import urlsplit

from starlette.requests import HTTPConnection, Request

from miss.server.accounts import User, session_for
from miss.server.core.errors import Forbidden, Unauthorized
from miss.server.storage.db import SessionRow
from miss.server.storage.store import Store

SESSION_COOKIE = "miss_session"
CSRF_COOKIE = "miss_csrf"
CSRF_HEADER = "x-csrf-token"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
LOGIN_HINT = "log in (POST /api/auth/login, or the page /login) and send the token"


def presented_token(headers: Mapping[str, str], cookies: Mapping[str, str]) -> tuple[str, bool]:
    """(token, came_by_cookie); ("", False) when there is none."""
    auth = headers.get("authorization", "")
    scheme, _, value = auth.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip(), False
    cookie = cookies.get(SESSION_COOKIE, "")
    return cookie, bool(cookie)


def authenticate(conn: HTTPConnection, store: Store) -> tuple[User, SessionRow, bool]:
    """The user behind a request or WebSocket; raises Unauthorized."""
    token, by_cookie = presented_token(conn.headers, conn.cookies)
    if not token:
        raise Unauthorized(f"not logged in; {LOGIN_HINT} as 'Authorization: Bearer TOKEN'.")
    found = session_for(store, token)
    if found is None:
        raise Unauthorized(f"the session is unknown or has expired; {LOGIN_HINT} again.")
    return found[0], found[1], by_cookie


def same_origin(conn: HTTPConnection) -> bool:
    """True when the request has no Origin (not sent by a page) or one naming this
    server's host; "null" (a sandboxed or file page) is foreign."""
    origin = conn.headers.get("origin")
    if origin is None:
        return True
    return urlsplit(origin).netloc.lower() == conn.headers.get("host", "").lower()


def check_csrf(request: Request, session: SessionRow) -> None:
    """Refuse a cookie-authenticated write from another site (see the module doc)."""
    if not same_origin(request):
        raise Forbidden("cross-site request refused; use MISS's own pages or a bearer token.")
    sent = request.headers.get(CSRF_HEADER, "")
    if not sent or not hmac.compare_digest(sent, session.csrf):
        raise Forbidden(
            "missing or wrong X-CSRF-Token header; send the value of the miss_csrf cookie "
            "with every write (or use 'Authorization: Bearer TOKEN')."
        )


def user_for_request(request: Request, store: Store) -> User:
    """The logged-in user of an HTTP request, CSRF checked for cookie writes."""
    user, session, by_cookie = authenticate(request, store)
    if by_cookie and request.method not in SAFE_METHODS:
        check_csrf(request, session)
    request.state.user = user
    return user


def page_user(request: Request, store: Store) -> User | None:
    """The user of a page request, or None (the page then redirects to the login)."""
    try:
        return authenticate(request, store)[0]
    except Unauthorized:
        return None


def can_see(user: User, owner_id: str | None) -> bool:
    """Owners see their own things, admins everything."""
    return user.is_admin or (owner_id is not None and owner_id == user.id)
