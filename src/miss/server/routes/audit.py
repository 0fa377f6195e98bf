"""``/api/audit``: the audit log, for administrators."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Query

from miss.server import audit
from miss.server.core.deps import AdminDep, StoreDep

router = APIRouter(prefix="/api/audit", tags=["audit"])


@router.get("")
def audit_log(
    store: StoreDep,
    admin: AdminDep,
    limit: Annotated[int, Query(ge=1, le=10_000, description="newest entries")] = 500,
    action: Annotated[str | None, Query(description=", ".join(audit.ACTIONS))] = None,
    actor: Annotated[str | None, Query(description="a user name or link:<share id>")] = None,
) -> list[dict[str, Any]]:
    """Who did what, when, from which address; oldest of the ``limit`` newest first."""
    return audit.entries(store, limit, action, actor)
