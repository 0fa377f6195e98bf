"""Security headers on every response of a real ``miss serve``: every route the app
declares is called (with real ids where it needs them, made-up ones elsewhere: a 404
must carry them too), plus unknown paths, a 405, a redirect, a 429 and static files."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from fastapi.routing import APIRoute
from starlette.routing import Route
from support.realserver import Server, serving

from miss.server.app import create_app
from miss.server.core.settings import Settings

REQUIRED = {
    "content-security-policy": "frame-ancestors 'none'",
    "x-content-type-options": "nosniff",
    "referrer-policy": "no-referrer",
    "x-frame-options": "DENY",
}


def check(r: httpx.Response, what: str) -> None:
    for name, must in REQUIRED.items():
        assert must in r.headers.get(name, ""), f"{what}: {r.status_code} without {name}: {must}"
    csp = r.headers["content-security-policy"]
    assert "default-src 'self'" in csp and " 'unsafe-eval'" not in csp
    if "script-src" in csp:
        assert "'unsafe-inline'" not in csp.split("script-src")[1].split(";")[0], csp


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    folder = tmp_path_factory.mktemp("headers")
    with serving(folder / "data", folder / "server.log") as running:
        yield running


def http_routes(tmp_path: Path) -> list[tuple[str, str]]:
    """(method, path template) of every HTTP route the app declares."""
    app = create_app(Settings(data_dir=tmp_path / "unused"))
    found = []
    for route in walk(app.routes):
        if isinstance(route, APIRoute | Route) and route.methods:
            found += [(m, route.path) for m in sorted(route.methods) if m != "HEAD"]
    return found


def walk(routes: list[Any]) -> Iterator[Any]:
    """Routes, those of included routers too (FastAPI keeps them behind a wrapper)."""
    for route in routes:
        inner = getattr(route, "original_router", None)
        yield from walk(inner.routes) if inner is not None else [route]


def fill(template: str, ids: dict[str, str]) -> str:
    return re.sub(r"\{(\w+)(:path)?\}", lambda m: ids.get(m.group(1), "x0"), template)


def test_every_route_answers_with_the_headers(server: Server, tmp_path: Path) -> None:
    volume = server.http.get("/api/volumes").json()[0]["id"]
    model = server.submit(volume, level=300, sample_rate=4)
    server.wait(model, ("done",))
    share = server.http.post("/api/shares", json={"model": model, "expires_in": 3600}).json()
    ids = {"volume_id": volume, "model_id": model, "share_id": share["id"], "axis": "axial",
           "index": "0", "fmt": "glb", "token": share["url"].rsplit("/", 1)[-1],
           "path": "js/api.js", "package": "three", "name": "admin"}  # fmt: skip
    routes = http_routes(tmp_path)
    assert len(routes) > 40
    visited = set()
    for method, template in routes:
        url = fill(template, ids)
        if template.startswith("/vendor/"):
            url = "/vendor/three/build/three.module.js"
        r = server.http.request(method, url, json={} if method in ("POST", "PATCH") else None)
        check(r, f"{method} {template}")
        visited.add((method, template))
    assert visited == set(routes)


def test_errors_redirects_and_limits_carry_the_headers(server: Server, tmp_path: Path) -> None:
    anonymous = httpx.Client(base_url=server.url)
    check(anonymous.get("/no/such/page"), "404 unknown path")
    check(anonymous.put("/api/health"), "405")
    r = anonymous.get("/", follow_redirects=False)
    assert r.status_code == 303
    check(r, "login redirect")
    check(anonymous.get("/api/volumes"), "401")
    check(anonymous.get("/static/css/miss.css"), "static file")
    check(anonymous.get("/docs"), "Swagger UI")
    check(anonymous.get("/redoc"), "ReDoc")
    assert "'unsafe-inline'" not in anonymous.get("/docs").headers["content-security-policy"]
    env = {"MISS_API_RATE": "0.01", "MISS_API_BURST": "1", "MISS_DEMO": "0"}
    with serving(tmp_path / "data", tmp_path / "limited.log", env=env) as limited:
        answers = [limited.http.get("/api/volumes") for _ in range(3)]
        assert answers[-1].status_code == 429
        check(answers[-1], "429 from the rate limiter")


def test_strict_transport_security_only_over_tls(server: Server) -> None:
    """HSTS over https only (a proxy that terminates TLS and says so): never on plain HTTP,
    where it would be ignored, or worse, pin a test host."""
    assert "strict-transport-security" not in server.http.get("/api/health").headers
