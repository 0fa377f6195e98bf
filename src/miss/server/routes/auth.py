"""``/api/auth``: log in (a token and the session cookie), log out, who am I; and
``/api/users`` for administrators."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Request, Response
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.concurrency import run_in_threadpool

from miss.errors import BadParameter, UnsupportedFormat
from miss.server import accounts, audit, quota
from miss.server.core.auth import CSRF_COOKIE, SESSION_COOKIE, presented_token
from miss.server.core.deps import (
    AdminDep,
    LoginLimitsDep,
    PasswordChecksDep,
    RoomsDep,
    SettingsDep,
    StoreDep,
    UserDep,
)
from miss.server.core.errors import Forbidden, Unauthorized
from miss.server.core.nextpath import safe_next
from miss.server.core.ratelimit import LoginLimits, OverLimit
from miss.server.core.schemas import JSONRoute
from miss.server.core.settings import Settings
from miss.server.rooms import Hub
from miss.server.storage.store import Store

router = APIRouter(tags=["accounts"], route_class=JSONRoute)


#: What the audit log records for a failed login with a name that is no account: never
#: the typed text (people type their password into the name field).
UNKNOWN_ACCOUNT = "(unknown account)"


class LoginRequest(BaseModel):
    """A login: user name, password and the page to go to afterwards."""

    model_config = ConfigDict(extra="forbid")

    username: str = Field(max_length=64)
    password: str = Field(max_length=1024)
    next: str = Field(
        default="/",
        max_length=16_384,
        description="the page to go to afterwards; the answer's next is this if it is a path "
        'on this server, else "/"',
    )


class UserOut(BaseModel):
    """An account as the API shows it (never its password)."""

    id: str
    name: str
    admin: bool
    disabled: bool = False
    pacs: bool = False


class NewUser(BaseModel):
    """A new account: its name, password (at least 8 characters) and permissions."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(max_length=64)
    password: str = Field(max_length=1024)
    admin: bool = False
    pacs: bool = Field(default=False, description="may search, import from and send to the PACS")


def user_out(user: accounts.User) -> UserOut:
    """The API's view of an account."""
    return UserOut(
        id=user.id, name=user.name, admin=user.is_admin, disabled=user.disabled, pacs=user.pacs
    )


def _require_json(request: Request) -> None:
    # A cross-site HTML form can post urlencoded or multipart bodies without a preflight,
    # never JSON: insisting on JSON keeps other sites from logging a browser in.
    if request.headers.get("content-type", "").split(";")[0].strip() != "application/json":
        raise UnsupportedFormat('send the login as JSON: {"username": ..., "password": ...}.')


@router.post(
    "/api/auth/login",
    responses={
        401: {"description": "wrong name or password"},
        429: {"description": "too many failed logins, or too many password checks at once"},
    },
)
async def login(
    body: LoginRequest,
    request: Request,
    store: StoreDep,
    settings: SettingsDep,
    limits: LoginLimitsDep,
    checks: PasswordChecksDep,
) -> JSONResponse:
    """Check name and password; answer ``{"token", "csrf", "expires", "user", "next"}``
    and set the session cookie (HttpOnly) and the CSRF cookie the pages echo in
    ``X-CSRF-Token``. ``next`` is the page to go to: the body's ``next`` if it is a path
    on this server (``nextpath.safe_next``), else "/"."""
    _require_json(request)
    where = audit.address(request)
    limits.attempt(where, body.username)  # counted first: raises 429 when locked
    try:
        user = await checks.run(_authenticate, store, body.username, body.password)
    except OverLimit:
        limits.succeeded(where, body.username)  # no password was checked: not a guess
        raise
    return await run_in_threadpool(_answer, body, request, store, settings, limits, where, user)


def _authenticate(
    store: Store, name: str, password: str
) -> accounts.User | None | accounts.Disabled:
    """The account, None for a wrong name or password, ``Disabled`` for the right password
    of a disabled account."""
    try:
        return accounts.authenticate(store, name, password)
    except accounts.Disabled as exc:
        return exc


def _answer(
    body: LoginRequest,
    request: Request,
    store: Store,
    settings: Settings,
    limits: LoginLimits,
    where: str,
    user: accounts.User | None | accounts.Disabled,
) -> JSONResponse:
    """The login's answer once the password was checked (database work: a thread)."""
    if isinstance(user, accounts.Disabled):
        audit.record(store, "login_disabled", body.username, where=where)
        raise Forbidden("this account is disabled; ask an administrator to enable it.")
    if user is None:
        known = accounts.exists(store, body.username)
        audit.record(
            store, "login_failed", body.username if known else UNKNOWN_ACCOUNT, where=where
        )
        raise Unauthorized("wrong user name or password.")
    limits.succeeded(where, body.username)
    token, csrf, expires = accounts.start_session(store, user, settings.session_hours)
    audit.record(store, "login", user.name, where=where)
    body_out = {
        "token": token,
        "csrf": csrf,
        "expires": expires.isoformat() + "Z",
        "user": user_out(user).model_dump(),
        "next": safe_next(body.next),
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
def logout(request: Request, store: StoreDep, user: UserDep, rooms: RoomsDep) -> Response:
    """End this session (the token stops working at once) and clear the cookies."""
    token, _ = presented_token(request.headers, request.cookies)
    rooms.end("session", accounts.end_session(store, token))
    audit.record(store, "logout", user.name, where=audit.address(request))
    response = Response(status_code=204)
    response.delete_cookie(SESSION_COOKIE, path="/")
    response.delete_cookie(CSRF_COOKIE, path="/")
    return response


@router.get("/api/auth/me", response_model=UserOut)
def me(user: UserDep) -> UserOut:
    """The account of this session (401 when not logged in)."""
    return user_out(user)


@router.get("/api/users", response_model=list[UserOut])
def list_users(store: StoreDep, admin: AdminDep) -> list[UserOut]:
    """Every account, oldest first; administrators only (403 otherwise)."""
    return [user_out(u) for u in accounts.list_users(store)]


class UsageOut(BaseModel):
    """What one account stores: volumes, models and their bytes on disk, against its quota."""

    account: str = Field(description='a user name; "" for what nobody owns (the demo)')
    volumes: int
    models: int = Field(description="models the account queued")
    bytes: int = Field(description="what its volumes and models take on disk")
    quota_bytes: int = Field(description="its quota (MISS_QUOTA_MB); 0: none")


@router.get("/api/admin/usage", response_model=list[UsageOut])
def usage(store: StoreDep, settings: SettingsDep, admin: AdminDep) -> list[UsageOut]:
    """Disk use per account, largest first (administrators)."""
    found = sorted(quota.usage(store).values(), key=lambda u: (-u.bytes, u.account))
    limit = settings.quota_bytes
    return [
        UsageOut(account=u.account, volumes=u.volumes, models=u.models, bytes=u.bytes,
                 quota_bytes=limit)
        for u in found
    ]  # fmt: skip


@router.post("/api/users", status_code=201, response_model=UserOut)
def add_user(body: NewUser, store: StoreDep, admin: AdminDep, request: Request) -> Any:
    """Create an account (administrators only); ``miss user add`` does the same offline."""
    user = accounts.create_user(store, body.name, body.password, body.admin, body.pacs)
    audit.record(
        store, "user_add", admin.name, user.name, audit.address(request),
        admin=body.admin, pacs=body.pacs,
    )  # fmt: skip
    return user_out(user)


class PasswordChange(BaseModel):
    """A change of one's own password: the current one and the new one."""

    model_config = ConfigDict(extra="forbid")

    old: str = Field(max_length=1024)
    new: str = Field(max_length=1024)


@router.post(
    "/api/auth/password",
    status_code=204,
    responses={403: {"description": "the old password is wrong"}},
)
async def change_password(
    body: PasswordChange,
    request: Request,
    store: StoreDep,
    user: UserDep,
    limits: LoginLimitsDep,
    checks: PasswordChecksDep,
    rooms: RoomsDep,
) -> Response:
    """Change your password (the old one first); every other login of yours ends, and
    their rooms close. This session stays."""
    where = audit.address(request)
    limits.attempt(where, user.name)  # the old password is a guess like any other
    try:
        right = await checks.run(accounts.check_password_of, store, user.id, body.old)
    except OverLimit:
        limits.succeeded(where, user.name)  # nothing was checked
        raise
    return await run_in_threadpool(
        _new_password, body, request, store, user, where, right, limits, rooms
    )


def _new_password(
    body: PasswordChange,
    request: Request,
    store: Store,
    user: accounts.User,
    where: str,
    right: bool,
    limits: LoginLimits,
    rooms: Hub,
) -> Response:
    """The password change once the old one was checked (database work: a thread)."""
    if not right:
        audit.record(store, "password_failed", user.name, where=where)
        raise Forbidden("the old password is wrong; type your current password.")
    limits.succeeded(where, user.name)
    accounts.set_password(store, user.id, body.new)
    token, _ = presented_token(request.headers, request.cookies)
    ended = accounts.end_sessions(store, user.id, keep=accounts.token_hash(token))
    for session in ended:
        rooms.end("session", session)
    audit.record(store, "password", user.name, where=where, sessions_ended=len(ended))
    return Response(status_code=204)


class UserChange(BaseModel):
    """An administrator's change to an account; fields left out stay as they are."""

    model_config = ConfigDict(extra="forbid")

    disabled: bool | None = Field(default=None, description="disable or enable the account")
    password: str | None = Field(default=None, max_length=1024, description="a new password")
    pacs: bool | None = Field(default=None, description="grant or take back the PACS permission")


@router.patch("/api/users/{name}", response_model=UserOut)
def change_user(
    name: str,
    body: UserChange,
    request: Request,
    store: StoreDep,
    admin: AdminDep,
    rooms: RoomsDep,
) -> Any:
    """Disable or enable an account, or set its password (administrators). Disabling and
    a new password end all of its logins at once, and close its rooms."""
    user = accounts.find_user(store, name)
    if body.disabled and user.id == admin.id:
        raise BadParameter("you cannot disable your own account; ask another administrator.")
    if body.password is not None:
        accounts.set_password(store, user.id, body.password)
    if body.disabled is not None:
        accounts.set_disabled(store, user.id, body.disabled)
    if body.pacs is not None:
        accounts.set_pacs(store, user.id, body.pacs)
    if body.password is not None or body.disabled:
        rooms.end("user", user.id)  # first: its rooms hear why
        accounts.end_sessions(store, user.id)
    changes = {k: v for k, v in (("disabled", body.disabled), ("pacs", body.pacs)) if v is not None}
    audit.record(
        store, "user_change", admin.name, user.name, audit.address(request),
        password_reset=body.password is not None, **changes,
    )  # fmt: skip
    return user_out(accounts.find_user(store, name))
