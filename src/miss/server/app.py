"""The application factory: ``create_app(settings)`` wires store, job queue and routes."""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from starlette.concurrency import run_in_threadpool

from miss import __version__
from miss.server import errors
from miss.server.ingest import register_demo
from miss.server.jobs import JobQueue
from miss.server.routes import models, pages, volumes
from miss.server.settings import Settings
from miss.server.store import Store

log = logging.getLogger("miss.server")


def _open(settings: Settings) -> tuple[Store, JobQueue]:
    """Prepare the data folder and database, register the demo, start the job threads."""
    store = Store(settings.data_dir, settings.database_url)
    store.init()
    if settings.demo and store.count_volumes() == 0:
        log.info("first start: registering the demo phantom")
        register_demo(store)
    queue = JobQueue(store, settings.workers)
    queue.start()
    return store, queue


def create_app(settings: Settings | None = None) -> FastAPI:
    """A MISS server app; ``settings`` default to the environment (``Settings.from_env``)."""
    settings = settings or Settings.from_env()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        store, queue = await run_in_threadpool(_open, settings)
        app.state.store, app.state.queue = store, queue
        try:
            yield
        finally:
            await run_in_threadpool(queue.stop)
            store.close()

    app = FastAPI(
        title="MISS - Medical Image Sharing System",
        version=__version__,
        description="Upload a CT/MRI scan, make 3-D surface models of it, view and download them.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    errors.install(app)
    app.include_router(volumes.router)
    app.include_router(models.router)
    app.include_router(pages.router)

    @app.get("/api/health", tags=["server"])
    def health() -> dict[str, str]:
        return {"status": "ok", "version": __version__}

    return app
