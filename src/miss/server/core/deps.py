"""Typed dependencies: what a route needs, looked up once (tests swap them via overrides)."""

from __future__ import annotations

import functools
import os
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from typing import Annotated, ParamSpec, TypeVar

import anyio.to_thread
from anyio import CapacityLimiter
from fastapi import Depends, Request
from starlette.concurrency import run_in_threadpool
from starlette.requests import HTTPConnection

from miss.server.accounts import User, session_cached
from miss.server.core.auth import can_see, presented_token, user_for_request
from miss.server.core.errors import Forbidden, NotFound
from miss.server.core.ratelimit import (
    ApiLimits,
    JobLimit,
    KeyedBuckets,
    LoginLimits,
    PasswordChecks,
)
from miss.server.core.settings import Settings
from miss.server.jobs import JobQueue
from miss.server.jobs.follow import Followers
from miss.server.metrics.registry import Metrics
from miss.server.pacs_exchange import PacsImports
from miss.server.rooms import Hub
from miss.server.storage.caches import ByteCaches
from miss.server.storage.db import ModelRow, VolumeRow
from miss.server.storage.store import Store
from miss.server.volumes.ingest import Reading
from miss.server.volumes.uploads import UploadSlots


# ``async``: a look-up on the app, answered on the event loop. FastAPI would otherwise
# run each of these in its threadpool, one thread hop per dependency per request.
async def get_settings(request: Request) -> Settings:
    """The server's settings, read once at start."""
    return request.app.state.settings


# ``HTTPConnection``: the look-ups a WebSocket route needs too.
async def get_store(conn: HTTPConnection) -> Store:
    """The store: database sessions, cached rows and the data folder."""
    return conn.app.state.store


async def get_queue(request: Request) -> JobQueue:
    """The queue that runs surface jobs."""
    return request.app.state.queue


async def get_job_limit(request: Request) -> JobLimit:
    """The limit on the jobs one account may have queued or running."""
    return request.app.state.job_limit


async def get_byte_caches(request: Request) -> ByteCaches:
    """This process's caches of model files and formats made on request."""
    return request.app.state.bytes


async def get_rooms(conn: HTTPConnection) -> Hub:
    """The hub of the live rooms (shared views of a model) of this process."""
    return conn.app.state.rooms


async def get_ws_connects(conn: HTTPConnection) -> KeyedBuckets:
    """The per-address buckets of WebSocket connections opened."""
    return conn.app.state.ws_connects


async def get_upload_slots(request: Request) -> UploadSlots:
    """The limit on uploads being received at once."""
    return request.app.state.upload_slots


async def get_reading(request: Request) -> Reading:
    """How uploads are read: the confinement probed at start and the parse limits."""
    return request.app.state.reading


async def get_pacs_imports(request: Request) -> PacsImports:
    """The imports from a PACS under way in this process."""
    return request.app.state.pacs_imports


async def get_password_checks(request: Request) -> PasswordChecks:
    """The limit on password checks at once in this process."""
    return request.app.state.password_checks


async def get_login_limits(request: Request) -> LoginLimits:
    """The per-address and per-account buckets of failed logins."""
    return request.app.state.failed_logins


async def get_metrics(request: Request) -> Metrics:
    """The Prometheus metrics of this process."""
    return request.app.state.metrics


@dataclass(frozen=True)
class ModelFiles:
    """What serving a model's files needs: the store, this process's byte caches, and the
    settings (the size of the cache of formats made on request)."""

    store: Store
    caches: ByteCaches
    settings: Settings


async def get_model_files(request: Request) -> ModelFiles:
    """What serving a model's files needs, in one value."""
    state = request.app.state
    return ModelFiles(state.store, state.bytes, state.settings)


P = ParamSpec("P")
T = TypeVar("T")


async def here_or_threadpool(
    in_memory: bool, fn: Callable[P, T], *args: P.args, **kwargs: P.kwargs
) -> T:
    """``fn(...)`` right here on the event loop when ``in_memory`` (the caller has seen
    that all ``fn`` reads is in this process's caches: no thread hop, no database); in
    the threadpool otherwise, where it may wait for the database or the disk."""
    if in_memory:
        return fn(*args, **kwargs)
    return await run_in_threadpool(fn, *args, **kwargs)


#: Slices one server process renders at once: one a core. A render reads and
#: decompresses chunks, holding the GIL part of the time; with the threadpool's 40 at once
#: (50 viewers arriving together) the event loop waited its turn behind them and cached
#: model fetches, answered on it, took 200-300 ms (benchmarks/load.py, PostgreSQL). The
#: others wait for a turn without taking the GIL; the cores were busy anyway.
RENDERS_AT_ONCE = max(1, os.cpu_count() or 1)


async def rendering(request: Request, fn: Callable[P, T], *args: P.args, **kwargs: P.kwargs) -> T:
    """``fn(...)`` in the threadpool, at most ``RENDERS_AT_ONCE`` of them at a time in
    this process (the app's own limiter, made on first use inside its event loop)."""
    state = request.app.state
    limiter = getattr(state, "renders", None)
    if limiter is None:
        limiter = state.renders = CapacityLimiter(RENDERS_AT_ONCE)
    call = functools.partial(fn, *args, **kwargs)
    return await anyio.to_thread.run_sync(call, limiter=limiter)


SettingsDep = Annotated[Settings, Depends(get_settings)]
StoreDep = Annotated[Store, Depends(get_store)]
QueueDep = Annotated[JobQueue, Depends(get_queue)]
JobLimitDep = Annotated[JobLimit, Depends(get_job_limit)]
BytesDep = Annotated[ByteCaches, Depends(get_byte_caches)]
RoomsDep = Annotated[Hub, Depends(get_rooms)]
#: WebSocket connections per client address (``MISS_WS_CONNECTS_PER_MINUTE``).
WsConnectsDep = Annotated[KeyedBuckets, Depends(get_ws_connects)]
UploadSlotsDep = Annotated[UploadSlots, Depends(get_upload_slots)]
ReadingDep = Annotated[Reading, Depends(get_reading)]
PacsImportsDep = Annotated[PacsImports, Depends(get_pacs_imports)]
PasswordChecksDep = Annotated[PasswordChecks, Depends(get_password_checks)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
LoginLimitsDep = Annotated[LoginLimits, Depends(get_login_limits)]
ModelFilesDep = Annotated[ModelFiles, Depends(get_model_files)]


# The look-ups below run on the event loop when the rows are cached (a viewer's usual
# request) and in the threadpool when they need the database (``here_or_threadpool``).
async def current_user(request: Request, store: StoreDep) -> User:
    """The logged-in user (bearer token or session cookie + CSRF); 401 otherwise."""
    token = presented_token(request.headers, request.cookies)[0]
    cached = not token or session_cached(store, token)  # no token: 401, nothing to read
    user = await here_or_threadpool(cached, user_for_request, request, store)
    # The API's rate limit counts this session's next requests against its account.
    limits: ApiLimits | None = getattr(request.app.state, "api_limits", None)
    if limits is not None:
        limits.remember(token, user.id)
    return user


UserDep = Annotated[User, Depends(current_user)]


async def event_stream(request: Request, user: UserDep) -> AsyncIterator[None]:
    """One of the account's open event streams (``MISS_SSE_PER_USER``; 429 beyond),
    held until the stream ends: FastAPI leaves a dependency with ``yield`` after the
    response has been sent."""
    with request.app.state.open_streams.slot(user.id):
        yield


EventStreamDep = Annotated[None, Depends(event_stream)]


def model_followers(request: Request) -> Followers:
    """This process's one look at each followed job (:mod:`miss.server.jobs.follow`)."""
    followers: Followers = request.app.state.followers
    return followers


FollowersDep = Annotated[Followers, Depends(model_followers)]


async def current_admin(user: UserDep) -> User:
    """The logged-in user if an administrator; 403 otherwise (401 when nobody is logged in)."""
    if not user.is_admin:
        raise Forbidden("only administrators may do this.")
    return user


AdminDep = Annotated[User, Depends(current_admin)]


def visible_volume(store: Store, user: User, volume_id: str) -> VolumeRow:
    """The volume if ``user`` may see it; otherwise the same 404 as for no volume at all,
    so nobody learns what exists."""
    row = store.get_volume(volume_id)
    if not can_see(user, row.owner_id):
        raise NotFound(f"no volume {volume_id!r}; GET /api/volumes lists the volumes.")
    return row


def visible_model(store: Store, user: User, model_id: str) -> ModelRow:
    """The model if ``user`` may see its volume; 404 otherwise (a missing model, or one not
    shared with ``user``: the message says whom to ask)."""
    row = store.get_model(model_id)
    owner = store.get_volume(row.volume_id).owner_id
    if not can_see(user, owner):
        # Only a signed-in account of this server gets here (401 before, else): a
        # colleague who was sent the owner's address, and needs to know what to ask for.
        raise NotFound(
            f"model {model_id!r} is not shared with you; ask its owner for a share link "
            "(the Share… button on the model's page)."
        )
    return row


async def get_volume_row(volume_id: str, store: StoreDep, user: UserDep) -> VolumeRow:
    """The volume named in the path, or 404 before the route (or its stream) starts."""
    cached = store.cached_volume(volume_id) is not None
    return await here_or_threadpool(cached, visible_volume, store, user, volume_id)


async def get_model_row(model_id: str, store: StoreDep, user: UserDep) -> ModelRow:
    """The model named in the path, or 404 before the route (or its stream) starts."""
    model = store.cached_model(model_id)
    cached = model is not None and store.cached_volume(model.volume_id) is not None
    return await here_or_threadpool(cached, visible_model, store, user, model_id)


VolumeDep = Annotated[VolumeRow, Depends(get_volume_row)]
ModelDep = Annotated[ModelRow, Depends(get_model_row)]
