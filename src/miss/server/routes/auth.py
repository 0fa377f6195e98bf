"""``/api/auth``: log in (a token and the session cookie), log out, who am I; and
``/api/users`` for administrators."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field

from miss.errors import UnsupportedFormat
from miss.server import accounts, audit
from miss.server.auth import CSRF_COOKIE, SESSION_COOKIE, presented_token
from miss.server.deps import AdminDep, SettingsDep, StoreDep, UserDep
from miss.server.errors import Unauthorized
from miss.server.ratelimit import KeyedBuckets, OverLimit
from miss.server.schemas import JSONRoute

router = APIRouter(tags=["accounts"], route_class=JSONRoute)


def failed_login_limits() -> KeyedBuckets:
    """Failed logins per client address: 10 at once, then one every 30 s. Enough for a
    person who mistypes, far too few to guess a password. One set per app."""
    return KeyedBuckets(capacity=10, rate=1 / 30)


class LoginRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    username: str = Field(max_length=64)
    password: str = Field(max_length=1024)


class UserOut(BaseModel):
    id: str
    name: str
    admin: bool


class NewUser(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str = Field(max_length=64)
    password: str = Field(max_length=1024)
    admin: bool = False


def user_out(user: accounts.User) -> UserOut:
    return UserOut(id=user.id, name=user.name, admin=user.is_admin)


def _require_json(request: Request) -> None:
    # A cross-site HTML form can post urlencoded or multipart bodies without a preflight,
    # never JSON: insisting on JSON keeps other sites from logging a browser in.
    if request.headers.get("content-type", "").split(";")[0].strip() != "application/json":
        raise UnsupportedFormat('send the login as JSON: {"username": ..., "password": ...}.')


@router.post(
    "/api/auth/login",
    responses={401: {"description": "wrong name or password"}, 429: {"description": "too many"}},
)
def login(
    body: LoginRequest, request: Request, store: StoreDep, settings: SettingsDep
) -> JSONResponse:
    """Check name and password; answer ``{"token", "csrf", "expires", "user"}`` and set the
    session cookie (HttpOnly) and the CSRF cookie the pages echo in ``X-CSRF-Token``."""
    _require_json(request)
    where = audit.address(request)
    limits: KeyedBuckets = request.app.state.failed_logins
    allowed, wait = limits.allowed(where)
    if not allowed:
        raise OverLimit(f"too many failed logins from {where}; try again in {wait:.0f} s.", wait)
    user = accounts.authenticate(store, body.username, body.password)
    if user is None:
        limits.take(where)
        audit.record(store, "login_failed", body.username[:64], where=where)
        raise Unauthorized("wrong user name or password.")
    token, csrf, expires = accounts.start_session(store, user, settings.session_hours)
    audit.record(store, "login", user.name, where=where)
    body_out = {
        "token": token,
        "csrf": csrf,
        "expires": expires.isoformat() + "Z",
        "user": user_out(user).model_dump(),
    }
    response = JSONResponse(body_out, headers={"Cache-Control": "no-store"})
    _set_cookies(response, request, token, csrf, int(settings.session_hours * 3600))
    return response


def _set_cookies(response: Response, request: Request, token: str, csrf: str, age: int) -> None:
    secure = request.url.scheme == "https"
    response.set_cookie(
        SESSION_COOKIE, token, max_age=age, path="/", httponly=True, samesite="lax", secure=secure
    )
    response.set_cookie(CSRF_COOKIE, csrf, max_age=age, path="/", samesite="strict", secure=secure)


@router.post("/api/auth/logout", status_code=204)
def logout(request: Request, store: StoreDep, user: UserDep) -> Response:
    """End this session (the token stops working at once) and clear the cookies."""
    token, _ = presented_token(request.headers, request.cookies)
    accounts.end_session(store, token)
    audit.record(store, "logout", user.name, where=audit.address(request))
    response = Response(status_code=204)
    response.delete_cookie(SESSION_COOKIE, path="/")
    response.delete_cookie(CSRF_COOKIE, path="/")
    return response


@router.get("/api/auth/me", response_model=UserOut)
def me(user: UserDep) -> UserOut:
    return user_out(user)


@router.get("/api/users", response_model=list[UserOut])
def list_users(store: StoreDep, admin: AdminDep) -> list[UserOut]:
    return [user_out(u) for u in accounts.list_users(store)]


@router.post("/api/users", status_code=201, response_model=UserOut)
def add_user(body: NewUser, store: StoreDep, admin: AdminDep, request: Request) -> Any:
    """Create an account (administrators only); ``miss user add`` does the same offline."""
    user = accounts.create_user(store, body.name, body.password, body.admin)
    audit.record(store, "user_add", admin.name, user.name, audit.address(request), admin=body.admin)
    return user_out(user)
