"""What operators watch: ``GET /api/health`` (``?deep=1``: the database, the data folder
and the job runners checked) and ``GET /metrics`` in Prometheus's text format.

``/metrics`` is for administrators: an administrator's session, or the bearer token set
in ``MISS_METRICS_TOKEN`` (what a Prometheus scraper is given; sessions expire). It
holds requests by route and status, their latency, jobs by state and how long they took,
and the room connections.

Whichever process answers, the numbers are those of every server process of its host
that shares the data folder (``miss serve --processes N`` behind one port, or several
``miss serve``): requests, latencies and job times summed over them, those of processes
that have exited included (the totals never go back while any server runs; they start
from zero again when the first server starts after all had stopped, as after a
restart); room connections summed over the running ones (``metrics.files``). Jobs by state
come from the shared database: the same on every host. Several hosts on one data folder
each answer for their own processes: scrape one process per host.
"""

from __future__ import annotations

import hmac
import os
import secrets
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import GaugeMetricFamily
from prometheus_client.registry import Collector
from sqlalchemy import func, select, text
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from miss.server.metrics.files import (
    FolderCollector,
    SampleFiles,
    SharedCounter,
    SharedHistogram,
    SharedLiveSum,
    host_folder,
)
from miss.server.storage.db import ModelRow
from miss.server.storage.store import Store

#: Seconds; from a cached model fetch (ms) to a slow upload.
LATENCY_BUCKETS = (0.001, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10, 30, 120)
JOB_BUCKETS = (1, 2, 5, 10, 20, 30, 60, 120, 300, 600, 1800, 3600)


class Metrics:
    """The server's metrics, in this app's files in the host's folder of the data folder
    (``files.host_folder``); ``text()`` reads every process's files there."""

    def __init__(self, data_dir: Path) -> None:
        self.files = SampleFiles(host_folder(data_dir))
        self.requests = SharedCounter(
            self.files,
            "miss_http_requests",
            "HTTP requests answered, by method, route (its template) and status.",
            ["method", "route", "status"],
        )
        self.latency = SharedHistogram(
            self.files,
            "miss_http_request_seconds",
            "Time from a request's arrival to the end of its answer, by route.",
            ["method", "route"],
            LATENCY_BUCKETS,
        )
        self.jobs = SharedHistogram(
            self.files,
            "miss_job_seconds",
            "Wall time of the jobs run, by outcome (done, failed, requeued).",
            ["outcome"],
            JOB_BUCKETS,
        )
        self.rooms = SharedLiveSum(
            self.files,
            "miss_room_connections",
            "Room WebSocket connections open on the running server processes.",
        )
        self.registry = CollectorRegistry()
        self.registry.register(FolderCollector(self.files.folder))

    def start(self, alone: bool) -> None:
        """Sweep the files of processes that are gone (all of them when ``alone``: the
        first server to start on the data folder) and show no room connections yet."""
        self.files.sweep(alone)
        self.rooms.set(0)

    def stop(self) -> None:
        """Close this process's sample files."""
        self.files.close()

    def watch(self, store: Callable[[], Store | None]) -> None:
        """Add what is read at scrape time: jobs by state."""
        self.registry.register(_Jobs(store))

    def text(self) -> bytes:
        """The registry in the Prometheus text format, as served at ``/metrics``."""
        return generate_latest(self.registry)


class _Jobs(Collector):
    def __init__(self, store: Callable[[], Store | None]) -> None:
        self.store = store

    def collect(self) -> Iterator[Any]:
        store = self.store()
        if store is None:
            return
        jobs = GaugeMetricFamily("miss_jobs", "Jobs (models) by state.", labels=["state"])
        query = select(ModelRow.status, func.count()).group_by(ModelRow.status)
        with store.session() as s:
            counts = {status: n for status, n in s.execute(query)}
        for state in ("queued", "running", "done", "failed"):
            jobs.add_metric([state], counts.get(state, 0))
        yield jobs


class RequestMetrics:
    """ASGI middleware counting each HTTP request by its route's template (``/api/models/
    {model_id}``, never the id: a bounded number of series) and timing it."""

    def __init__(self, app: ASGIApp, metrics: Metrics) -> None:
        self.app, self.metrics = app, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Count and time each HTTP request by method, route template and status."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start = time.perf_counter()
        status = 500

        async def sending(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, sending)
        finally:
            route = getattr(scope.get("route"), "path", None) or "(no route)"
            method = scope.get("method", "")
            self.metrics.requests.inc(method, route, str(status))
            self.metrics.latency.observe(method, route, value=time.perf_counter() - start)


def scrape_token(env: dict[str, str] | None = None) -> str:
    """``MISS_METRICS_TOKEN`` ("" when unset: administrators' sessions only)."""
    return (os.environ if env is None else env).get("MISS_METRICS_TOKEN", "").strip()


def is_scraper(authorization: str, token: str) -> bool:
    """True when ``Authorization: Bearer <token>`` carries the scrape token."""
    if not token or not authorization.lower().startswith("bearer "):
        return False
    return hmac.compare_digest(authorization[7:].strip().encode(), token.encode())


def check_database(store: Store) -> dict[str, Any]:
    """Run ``SELECT 1``; ``{"ok": True, "ms": round trip in milliseconds}`` (raises what the
    database raises when it is unreachable)."""
    start = time.perf_counter()
    with store.engine.connect() as conn:
        conn.execute(text("SELECT 1"))
    return {"ok": True, "ms": round(1000 * (time.perf_counter() - start), 1)}


def check_data_folder(store: Store, min_free: int) -> dict[str, Any]:
    """The folder is there, writable (a file made and removed in ``tmp/``) and has room."""
    probe = store.data_dir / "tmp" / f".health-{secrets.token_hex(4)}"
    probe.write_bytes(b"ok")
    probe.unlink()
    free = store.free_bytes()
    return {"ok": free >= min_free, "free_mb": round(free / 2**20)}
