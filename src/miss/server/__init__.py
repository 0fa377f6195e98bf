"""The MISS web system: REST API, job workers and the pages (``miss serve``).

``create_app(settings)`` builds the FastAPI app; ``main.serve`` runs it under uvicorn.

Both load on first use, not with the package: ``miss.server.storage.chunked`` (a volume
on disk) is what a Dask worker unpickles with a block's task, and FastAPI, SQLAlchemy and
the routes took 0.84 s to import with it, inside the cluster's first job.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from miss.server.app import create_app
    from miss.server.core.settings import Settings

__all__ = ["Settings", "create_app"]


def __getattr__(name: str) -> Any:
    if name == "create_app":
        from miss.server.app import create_app

        return create_app
    if name == "Settings":
        from miss.server.core.settings import Settings

        return Settings
    raise AttributeError(f"module 'miss.server' has no attribute {name!r}")
