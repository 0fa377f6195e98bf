"""The MISS web system: REST API, job workers and the pages (``miss serve``).

``create_app(settings)`` builds the FastAPI app; ``main.serve`` runs it under uvicorn.
"""

from __future__ import annotations

from miss.server.app import create_app
from miss.server.settings import Settings

__all__ = ["Settings", "create_app"]
