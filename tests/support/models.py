"""Waiting for a model job, the same way for a TestClient, a real server and a browser test."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

#: Seconds a test waits for a job on a busy machine before it fails.
JOB_TIMEOUT = 120.0
FINISHED = ("done", "failed")


def wait_for_model(
    client: Any,
    model_id: str,
    until: tuple[str, ...] = FINISHED,
    timeout: float = JOB_TIMEOUT,
    poll: float = 0.2,
) -> dict[str, Any]:
    """Poll ``client.get("/api/models/<id>")`` until the model's status is in ``until``.

    Parameters
    ----------
    client : TestClient, httpx.Client, support.realserver.Server or callable
        Its ``get(path)`` (or itself, called with the path) returns the JSON body or a
        response with ``json()``.
    model_id : str
        The model to wait for.
    until : tuple of str
        Statuses that end the wait.
    timeout, poll : float
        Seconds before the test fails, and between two requests.
    """
    get: Callable[[str], Any] = client.get if hasattr(client, "get") else client
    deadline = time.monotonic() + timeout
    while True:
        body = get(f"/api/models/{model_id}")
        body = body.json() if hasattr(body, "json") else body
        if body["status"] in until:
            return body
        if time.monotonic() >= deadline:
            raise AssertionError(f"model {model_id} not {until} after {timeout} s: {body}")
        time.sleep(poll)
