"""``miss serve``: run the app under uvicorn."""

from __future__ import annotations

import logging
import os
import sys

import uvicorn

from miss.server.app import create_app
from miss.server.core import logmask
from miss.server.core.settings import Settings
from miss.server.rooms import MAX_MESSAGE_BYTES
from miss.server.storage.private import owner_only
from miss.server.storage.store import DataDirInUse, Store


def serve(
    host: str | None = None,
    port: int | None = None,
    data_dir: str | None = None,
    processes: int = 1,
) -> int:
    """Serve MISS until interrupted; arguments override the environment's settings.

    ``processes`` > 1: that many server processes on the one port (uvicorn's workers),
    which needs PostgreSQL (``MISS_DATABASE_URL``): they share it and the data folder.
    """
    try:
        settings = Settings.from_env(host=host, port=port, data_dir=data_dir)
    except ValueError as exc:
        print(f"miss: {exc}", file=sys.stderr)
        return 2
    if processes < 1 or (processes > 1 and not settings.database_url.startswith("postgresql")):
        print(
            f"miss: --processes {processes}: give 1, or more with MISS_DATABASE_URL pointing "
            "at PostgreSQL (several processes share its database; SQLite takes one).",
            file=sys.stderr,
        )
        return 2
    owner_only(settings.data_dir, settings.database_url)  # before anything is written
    probe = Store(settings.data_dir, settings.database_url)
    try:  # say it in one line now rather than as a traceback from the app's startup
        probe.lock()
    except DataDirInUse as exc:
        print(f"miss: {exc}", file=sys.stderr)
        return 1
    finally:
        probe.close()
    logging.basicConfig(level=logging.INFO, format="%(levelname)s:     %(name)s: %(message)s")
    shown = "localhost" if settings.host in ("127.0.0.1", "0.0.0.0", "::") else settings.host
    url = f"http://{shown}:{settings.port}/"
    print(f"MISS serving {settings.data_dir} at {url}  (API docs: {url}docs)", flush=True)
    options: dict[str, object] = {
        "host": settings.host,
        "port": settings.port,
        "log_level": "info",
        # Frames far beyond a room's message limit are cut off by the protocol (1009)
        # before they are buffered whole; the room refuses the ones in between itself.
        "ws_max_size": 4 * MAX_MESSAGE_BYTES,
        # uvicorn believes X-Forwarded-For from 127.0.0.1 unless told not to: anyone on
        # the machine could then pose as any address and skip every per-address limit.
        # The app reads the headers itself, from MISS_TRUSTED_PROXIES only (``app``).
        "proxy_headers": False,
    }
    if processes > 1:
        # Each process reads its settings from the environment (``app_from_env``).
        os.environ.update(MISS_HOST=settings.host, MISS_PORT=str(settings.port))
        os.environ["MISS_DATA_DIR"] = str(settings.data_dir)
        uvicorn.run("miss.server.main:app_from_env", factory=True, workers=processes, **options)  # type: ignore[arg-type]
        return 0
    config = uvicorn.Config(create_app(settings), **options)  # type: ignore[arg-type]
    # After uvicorn set up its loggers: share tokens in paths never reach the log.
    logmask.install("uvicorn.access", "uvicorn.error", "miss.server")
    uvicorn.Server(config).run()
    return 0


def app_from_env() -> object:
    """The app of one of ``miss serve --processes N``'s processes."""
    logmask.install("uvicorn.access", "uvicorn.error", "miss.server")
    return create_app(Settings.from_env())
