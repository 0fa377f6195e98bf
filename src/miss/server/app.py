"""The application factory: ``create_app(settings)`` wires store, job queue, rooms and
routes."""

from __future__ import annotations

import logging
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool
from uvicorn.middleware.proxy_headers import ProxyHeadersMiddleware

from miss import __version__
from miss.io import confined
from miss.server.accounts import ADMIN_NAME, ensure_admin
from miss.server.core import errors
from miss.server.core.headers import SecurityHeaders
from miss.server.core.ratelimit import (
    ApiLimits,
    JobLimit,
    LoginLimits,
    OpenStreams,
    OverLimit,
    PasswordChecks,
    RateLimitMiddleware,
    SharedBuckets,
    too_many,
    ws_connect_limits,
)
from miss.server.core.settings import Settings
from miss.server.jobs import JobQueue, WorkerProcess
from miss.server.jobs.follow import Followers
from miss.server.metrics.registry import Metrics, RequestMetrics
from miss.server.pacs_exchange import PacsImports, fail_interrupted
from miss.server.rooms import Hub
from miss.server.routes import (
    audit,
    auth,
    health,
    models,
    pacs,
    pages,
    rooms,
    shares,
    volumes,
    voxels,
)
from miss.server.routes.pages import WEB
from miss.server.storage.caches import ByteCaches
from miss.server.storage.store import CHUNK_CACHE, Store
from miss.server.volumes.ingest import register_demo
from miss.server.volumes.uploads import UploadSlots

log = logging.getLogger("miss.server")


def _open(settings: Settings, metrics: Metrics | None = None) -> tuple[Store, JobQueue]:
    """Prepare the data folder and database, make the first administrator, register the
    demo, start the job threads."""
    store = Store(
        settings.data_dir, settings.database_url, settings.in_memory_max_bytes, CHUNK_CACHE
    )
    store.init()
    if metrics is not None:
        metrics.start(alone=store.alone)
    if settings.demo and store.count_volumes() == 0:
        log.info("first start: registering the demo phantom")
        register_demo(store)
    _first_admin(store, settings)
    store.appender.start()
    runner = WorkerProcess(store, settings.spare_workers, settings.job_env())
    queue = JobQueue(
        store, settings.workers, runner, settings.job_cpu_seconds, settings.workers_per_account
    )
    if metrics is not None:
        queue.on_finished = lambda outcome, seconds: metrics.jobs.observe(outcome, value=seconds)
    queue.start()
    if store.alone:  # no other server of this data folder is importing
        fail_interrupted(store)
    store.share()  # started: other servers of the same PostgreSQL database may start too
    return store, queue


def _first_admin(store: Store, settings: Settings) -> None:
    """Create ``admin`` on a database without users; a made-up password is printed once,
    to the console only (never to the log file)."""
    made_up = ensure_admin(store, settings.admin_password)
    if made_up:
        print(
            f"\nMISS: created the administrator '{ADMIN_NAME}' with the password:  {made_up}\n"
            "      It is shown only this once; log in with it and keep it somewhere safe "
            "(or set MISS_ADMIN_PASSWORD before the first start).\n",
            file=sys.stderr,
            flush=True,
        )


def _say_confinement(confinement: confined.Confinement) -> None:
    """One line at start: how uploads are read, and what is refused when not confined."""
    if confinement.confined:
        log.info("uploads are read in a confined process: %s", confinement.mechanism)
        return
    print(
        f"MISS: uploads are NOT confined ({confinement.problem}); detached NRRD/MetaImage "
        "headers and formats only SimpleITK reads are refused.",
        file=sys.stderr,
        flush=True,
    )
    log.warning("uploads not confined: %s", confinement.problem)


async def _over_limit(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, OverLimit)
    log.info("%s %s -> 429: %s", request.method, request.url.path, exc)
    return too_many(str(exc), exc.wait)


def create_app(settings: Settings | None = None) -> FastAPI:  # noqa: PLR0915 (to split: issue 40)
    """A MISS server app; ``settings`` default to the environment (``Settings.from_env``)."""
    settings = settings or Settings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        store, queue = await run_in_threadpool(_open, settings, app.state.metrics)
        app.state.store, app.state.queue = store, queue
        confinement = await run_in_threadpool(confined.probe, settings.data_dir)
        _say_confinement(confinement)
        app.state.reading = (confinement, settings.parse_limits())
        app.state.pacs_imports = PacsImports(store, settings, lambda: app.state.reading)
        assert settings.room_reserved is not None  # Settings fills it in
        app.state.rooms = Hub(
            store,
            max_people=settings.room_max_people,
            reserved=settings.room_reserved,
            per_link=settings.room_guests_per_link,
        )
        app.state.rooms.on_people = app.state.metrics.rooms.set
        app.state.rooms.start()
        app.state.shared_limits.start(store.bus)
        store.bus.start()  # after every subscriber: the job queue, the rooms
        try:
            yield
        finally:
            app.state.pacs_imports.stop()
            app.state.shared_limits.stop()
            await app.state.rooms.stop()
            await run_in_threadpool(queue.stop)
            app.state.metrics.stop()
            store.close()

    app = FastAPI(
        title="MISS - Medical Image Sharing System",
        version=__version__,
        description="Upload a CT/MRI scan, make 3-D surface models of it, view and download "
        "them, share them by link and discuss them live. Log in with POST /api/auth/login and "
        "send 'Authorization: Bearer TOKEN'.",
        lifespan=lifespan,
        docs_url=None,  # served from npm packages by routes/pages.py: no CDN
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.bytes = ByteCaches()
    app.state.metrics = Metrics(settings.data_dir)
    app.state.metrics.watch(lambda: getattr(app.state, "store", None))
    app.state.failed_logins = LoginLimits()
    app.state.password_checks = PasswordChecks(settings.password_checks)
    app.state.api_limits = ApiLimits(settings.api_rate, settings.api_burst)
    app.state.ws_connects = ws_connect_limits(settings.ws_connects_per_minute)
    app.state.shared_limits = SharedBuckets(
        {
            "api": app.state.api_limits.buckets,
            "login-addresses": app.state.failed_logins.addresses,
            "login-accounts": app.state.failed_logins.accounts,
            "ws-connects": app.state.ws_connects,
        }
    )
    app.state.job_limit = JobLimit(settings.max_jobs_per_user)
    app.state.open_streams = OpenStreams(settings.sse_per_user)
    app.state.followers = Followers()
    app.state.upload_slots = UploadSlots(settings.uploads_per_user, settings.uploads_at_once)
    app.add_middleware(RateLimitMiddleware, limits=app.state.api_limits)
    # Added last, so outermost: the rate limiter's 429 and every error get the headers too,
    # and the request counts see every answer, 429s included.
    app.add_middleware(SecurityHeaders, pages=WEB)
    app.add_middleware(RequestMetrics, metrics=app.state.metrics)
    if settings.trusted_proxies:
        # Outermost: every limit and the audit see the client the proxy names. Only these
        # peers are believed; ``miss serve`` turns uvicorn's own reading of the headers off.
        app.add_middleware(ProxyHeadersMiddleware, trusted_hosts=list(settings.trusted_proxies))
    errors.install(app)
    app.add_exception_handler(OverLimit, _over_limit)
    app.include_router(auth.router)
    app.include_router(volumes.router)
    app.include_router(voxels.router)
    app.include_router(models.router)
    app.include_router(rooms.router)
    app.include_router(shares.router)
    app.include_router(audit.router)
    app.include_router(pacs.router)
    app.include_router(pages.router)
    app.include_router(health.router)
    return app
