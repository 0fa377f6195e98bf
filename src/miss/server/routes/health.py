"""What operators watch: ``GET /api/health`` (``?deep=1``: the database, the data folder
and the job runners checked) and ``GET /metrics`` in Prometheus's text format."""

from __future__ import annotations

import os
from typing import Any

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool

from miss import __version__
from miss.server.core import errors
from miss.server.core.deps import (
    MetricsDep,
    QueueDep,
    SettingsDep,
    StoreDep,
    current_admin,
    current_user,
)
from miss.server.core.settings import Settings
from miss.server.jobs import JobQueue
from miss.server.metrics.registry import check_data_folder, check_database, is_scraper, scrape_token
from miss.server.storage.store import Store

router = APIRouter()


@router.get("/api/health", tags=["server"], response_model=None)
async def health(
    request: Request,
    settings: SettingsDep,
    store: StoreDep,
    queue: QueueDep,
    deep: bool = False,
) -> dict[str, Any] | JSONResponse:
    """Without ``deep``: answered on the event loop itself (no thread, no database), its
    latency is the loop's, which load tests watch while jobs and uploads run. With
    ``?deep=1``: the database, the data folder and the job runners checked too; 503
    when any of them is not well (for a load balancer's health check). Only
    administrators and the scrape token read the details (free space, the errors)."""
    if not deep:
        return {"status": "ok", "version": __version__}
    checks = await run_in_threadpool(_deep_checks, settings, store, queue)
    well = all(c["ok"] for c in checks.values())
    body: dict[str, Any] = {"status": "ok" if well else "failing", "version": __version__}
    if await _is_operator(request, store):
        body |= checks
        body["process"] = os.getpid()  # which of several server processes answered
    else:
        body |= {name: {"ok": check["ok"]} for name, check in checks.items()}
    return JSONResponse(body, status_code=200 if well else 503)


@router.get("/metrics", tags=["server"], include_in_schema=False)
async def metrics(request: Request, store: StoreDep, registry: MetricsDep) -> Response:
    """Prometheus text format, for administrators or ``MISS_METRICS_TOKEN``'s bearer."""
    if not is_scraper(request.headers.get("authorization", ""), scrape_token()):
        await current_admin(await current_user(request, store))
    body = await run_in_threadpool(registry.text)
    return Response(body, media_type="text/plain; version=0.0.4; charset=utf-8")


async def _is_operator(request: Request, store: Store) -> bool:
    """An administrator's session or the scrape token (``MISS_METRICS_TOKEN``)."""
    if is_scraper(request.headers.get("authorization", ""), scrape_token()):
        return True
    try:
        await current_admin(await current_user(request, store))
    except (errors.Unauthorized, errors.Forbidden):
        return False
    return True


def _deep_checks(settings: Settings, store: Store, queue: JobQueue) -> dict[str, dict[str, Any]]:
    """Each check's answer, or its failure in words (never raised: the answer is the 503)."""
    checks = {
        "database": lambda: check_database(store),
        "data_folder": lambda: check_data_folder(store, settings.min_free_bytes),
        "job_runners": queue.health,
    }
    out: dict[str, dict[str, Any]] = {}
    for name, check in checks.items():
        try:
            out[name] = check()
        except Exception as exc:  # what an operator needs to read is the reason
            out[name] = {"ok": False, "error": f"{type(exc).__name__}: {exc}"[:300]}
    return out
