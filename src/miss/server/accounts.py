"""Users and their login sessions, in the database.

Passwords are stored as argon2id hashes (argon2-cffi's defaults: 64 MiB, 3 passes),
the salt inside the hash string. A session is a 256-bit random token handed to the
client once; the database keeps only its SHA-256, so a copy of the database opens
nothing. Each session also carries a CSRF value that cookie-authenticated writes echo.
"""

from __future__ import annotations

import hashlib
import re
import secrets
from dataclasses import dataclass
from datetime import datetime, timedelta

from argon2 import PasswordHasher
from argon2.exceptions import InvalidHashError, VerificationError
from sqlalchemy import delete, select, update
from sqlalchemy.exc import IntegrityError

from miss.errors import BadParameter
from miss.server.core.errors import NotFound
from miss.server.storage.db import SessionRow, UserRow, VolumeRow, utcnow
from miss.server.storage.store import Store, always, new_id

_HASHER = PasswordHasher()
#: A hash to verify against when the user does not exist, so a wrong name takes as long
#: as a wrong password and response times do not reveal which names exist.
_DUMMY_HASH = _HASHER.hash(secrets.token_urlsafe(16))
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._@-]{0,63}$")
MIN_PASSWORD = 8
ADMIN_NAME = "admin"


@dataclass(frozen=True)
class User:
    """Who a request acts for."""

    id: str
    name: str
    is_admin: bool
    disabled: bool = False
    #: May use the PACS (search, import, send); granted by an administrator.
    pacs: bool = False


def _user(row: UserRow) -> User:
    return User(
        id=row.id,
        name=row.name,
        is_admin=row.is_admin,
        disabled=bool(row.disabled),
        pacs=bool(row.pacs),
    )


def token_hash(token: str) -> str:
    """SHA-256 hex of a bearer or share token: what the database stores and looks up."""
    return hashlib.sha256(token.encode("utf-8", "replace")).hexdigest()


def check_name(name: str) -> str:
    """``name`` if it is a valid user name; BadParameter naming the allowed characters otherwise."""
    if not NAME_PATTERN.match(name):
        raise BadParameter(
            f"user name {name!r} is not valid; use 1-64 letters, digits, '.', '_', '@' or '-', "
            "starting with a letter or digit."
        )
    return name


def check_password(password: str) -> str:
    """``password`` if it is long enough (``MIN_PASSWORD`` characters); BadParameter otherwise."""
    if len(password) < MIN_PASSWORD:
        raise BadParameter(f"the password is too short; use at least {MIN_PASSWORD} characters.")
    return password


def create_user(
    store: Store, name: str, password: str, is_admin: bool = False, pacs: bool = False
) -> User:
    """Add an account; raises BadParameter for a bad or taken name, a short password."""
    row = UserRow(
        id=new_id(),
        name=check_name(name),
        password=_HASHER.hash(check_password(password)),
        is_admin=is_admin,
        pacs=pacs,
    )
    try:
        with store.session.begin() as s:
            s.add(row)
    except IntegrityError:
        raise BadParameter(f"a user named {name!r} exists already; choose another name.") from None
    return _user(row)


def list_users(store: Store) -> list[User]:
    """Every account, oldest first."""
    with store.session() as s:
        return [_user(r) for r in s.scalars(select(UserRow).order_by(UserRow.created_at))]


def get_user(store: Store, user_id: str) -> User | None:
    """The account with id ``user_id``, or None when there is none."""
    with store.session() as s:
        row = s.get(UserRow, user_id)
    return _user(row) if row else None


class Disabled(Exception):
    """The right password of an account an administrator has disabled."""


def exists(store: Store, name: str) -> bool:
    """Whether an account called ``name`` exists."""
    with store.session() as s:
        return s.scalars(select(UserRow.id).where(UserRow.name == name)).first() is not None


def authenticate(store: Store, name: str, password: str) -> User | None:
    """The user whose name and password these are, else None (in constant-ish time).

    Raises ``Disabled`` for the right password of a disabled account: only someone who
    knows the password learns that the account exists and is disabled.
    """
    with store.session() as s:
        row = s.scalars(select(UserRow).where(UserRow.name == name)).first()
    try:
        _HASHER.verify(row.password if row else _DUMMY_HASH, password)
    except (VerificationError, InvalidHashError):
        return None
    if row is None:
        return None
    if row.disabled:
        raise Disabled(name)
    if _HASHER.check_needs_rehash(row.password):  # the library's defaults grew stronger
        with store.session.begin() as s:
            s.execute(
                update(UserRow).where(UserRow.id == row.id).values(password=_HASHER.hash(password))
            )
    return _user(row)


def start_session(store: Store, user: User, hours: float) -> tuple[str, str, datetime]:
    """A new login for ``user``: (token, csrf, expires); only the token's hash is kept."""
    token, csrf = secrets.token_urlsafe(32), secrets.token_urlsafe(24)
    expires = utcnow() + timedelta(hours=hours)
    with store.session.begin() as s:
        s.execute(delete(SessionRow).where(SessionRow.expires_at < utcnow()))
        s.add(SessionRow(id=token_hash(token), user_id=user.id, csrf=csrf, expires_at=expires))
    return token, csrf, expires


def session_for(store: Store, token: str) -> tuple[User, SessionRow] | None:
    """The user and live session of a bearer token, or None (unknown or expired).

    Live sessions are kept in ``store.rows``: only this server starts and ends them
    (``miss user`` adds accounts, never sessions), so a hit is as good as a query.
    """
    key = ("session", token_hash(token))
    found = store.rows.cached(key, lambda: _load_session(store, key[1]), always)
    if found is None or found[1].expires_at <= utcnow():
        return None
    return found


def session_cached(store: Store, token: str) -> bool:
    """True when ``session_for(store, token)`` will answer from memory (never waits)."""
    return store.rows.get(("session", token_hash(token))) is not None


def _load_session(store: Store, hashed: str) -> tuple[User, SessionRow] | None:
    with store.session() as s:
        found = s.execute(
            select(UserRow, SessionRow)
            .join(SessionRow, SessionRow.user_id == UserRow.id)
            .where(SessionRow.id == hashed, SessionRow.expires_at > utcnow())
            .where(UserRow.disabled.is_(False))
        ).first()
    return (_user(found[0]), found[1]) if found else None


def end_session(store: Store, token: str) -> str:
    """End one login; returns its session id (the token's hash)."""
    hashed = token_hash(token)
    with store.session.begin() as s:
        s.execute(delete(SessionRow).where(SessionRow.id == hashed))
    store.rows.drop(("session", hashed))
    return hashed


def end_sessions(store: Store, user_id: str, keep: str | None = None) -> list[str]:
    """End every login of ``user_id`` but the session ``keep``; returns the ended ids."""
    with store.session.begin() as s:
        ended = list(
            s.scalars(
                select(SessionRow.id).where(SessionRow.user_id == user_id, SessionRow.id != keep)
            )
        )
        s.execute(delete(SessionRow).where(SessionRow.id.in_(ended)))
    store.rows.drop(*[("session", hashed) for hashed in ended])
    return ended


def find_user(store: Store, name: str) -> User:
    """The account called ``name``; NotFound when there is none."""
    with store.session() as s:
        row = s.scalars(select(UserRow).where(UserRow.name == name)).first()
    if row is None:
        raise NotFound(f"no user named {name!r}; GET /api/users lists them.")
    return _user(row)


def set_password(store: Store, user_id: str, password: str) -> None:
    """Replace the account's password (checked for length, stored hashed); BadParameter
    when it is too short."""
    hashed = _HASHER.hash(check_password(password))
    with store.session.begin() as s:
        s.execute(update(UserRow).where(UserRow.id == user_id).values(password=hashed))


def check_password_of(store: Store, user_id: str, password: str) -> bool:
    """Whether ``password`` is the account's current one."""
    with store.session() as s:
        row = s.get(UserRow, user_id)
    try:
        return row is not None and _HASHER.verify(row.password, password)
    except (VerificationError, InvalidHashError):
        return False


def set_disabled(store: Store, user_id: str, disabled: bool) -> None:
    """Disable or enable the account again: a disabled account can no longer log in, and
    its logins are refused from their next request once the cached rows are dropped
    (``announce_change``)."""
    with store.session.begin() as s:
        s.execute(update(UserRow).where(UserRow.id == user_id).values(disabled=disabled))


def set_pacs(store: Store, user_id: str, allowed: bool) -> None:
    """Grant or take back the ``pacs`` permission; the account's logins see it at their
    next request (their cached rows are dropped, the logins go on)."""
    with store.session.begin() as s:
        s.execute(update(UserRow).where(UserRow.id == user_id).values(pacs=allowed))
        live = list(s.scalars(select(SessionRow.id).where(SessionRow.user_id == user_id)))
    store.rows.drop(*[("session", hashed) for hashed in live])


def announce_change(store: Store, user_id: str, end_rooms: bool = False) -> None:
    """Tell every server process of this database that ``user_id``'s account changed
    (``miss user`` runs beside them): each empties its cached rows, so the account's
    logins are read again at their next request (a disabled account, an ended login or
    a permission taken back counts at once), and with ``end_rooms`` closes the account's
    room connections. Heard within a second (``Bus.announce``: on SQLite too)."""
    store.rows.clear_here()
    store.bus.announce("rows", None)
    if end_rooms:
        store.bus.announce("ended", ["user", user_id])


def ensure_admin(store: Store, password: str = "") -> str | None:
    """On a database without administrators, create ``admin``; returns the password when it was
    made up here (to be shown once), None otherwise. Volumes without an owner (the demo,
    uploads from before accounts) are given to the first admin."""
    made_up = None
    if not any(u.is_admin for u in list_users(store)):
        made_up = None if password else secrets.token_urlsafe(12)
        create_user(store, ADMIN_NAME, password or made_up or "", is_admin=True)
    with store.session() as s:
        admin = s.scalars(
            select(UserRow.id).where(UserRow.is_admin).order_by(UserRow.created_at)
        ).first()
    if admin is not None:
        with store.session.begin() as s:
            s.execute(update(VolumeRow).where(VolumeRow.owner_id.is_(None)).values(owner_id=admin))
        store.rows.clear()  # volumes may have been read before they had an owner
    return made_up
