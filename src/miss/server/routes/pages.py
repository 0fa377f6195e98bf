"""The browser pages and their files: the login, the library, a volume, the viewer;
static JS/CSS; three.js from ``web/node_modules`` (installed by ``make`` from npm, served
locally). Pages other than the login need a session; without one they redirect to it."""

from __future__ import annotations

import re
from pathlib import Path
from urllib.parse import quote

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, RedirectResponse, Response

import miss
from miss.server import audit
from miss.server.accounts import User
from miss.server.auth import page_user
from miss.server.deps import StoreDep, visible_model
from miss.server.errors import NotFound
from miss.server.storage.store import Store

WEB = Path(miss.__file__).parent / "web"
THREE = WEB / "node_modules" / "three"
#: npm packages served under /vendor/NAME/ (only the files they ship for browsers).
VENDOR = {
    "three": THREE,
    "swagger-ui": WEB / "node_modules" / "swagger-ui-dist",
    "redoc": WEB / "node_modules" / "redoc" / "bundles",
}
#: Types the stdlib may not know (or knows differently per platform): ES modules must
#: come as JavaScript or the browser refuses to run them.
TYPES = {
    ".js": "text/javascript",
    ".mjs": "text/javascript",
    ".css": "text/css",
    ".html": "text/html",
    ".json": "application/json",
    ".wasm": "application/wasm",
    ".svg": "image/svg+xml",
    ".png": "image/png",
    ".glb": "model/gltf-binary",
}

router = APIRouter(include_in_schema=False)


def safe_file(root: Path, relative: str, forbid: tuple[str, ...] = ("node_modules",)) -> Path:
    """``root/relative`` if it is a file inside ``root`` (no ``..``, no ``forbid`` folders)."""
    parts = Path(relative).parts
    if not relative or ".." in parts or set(forbid) & set(parts) or relative.startswith("/"):
        raise NotFound(f"no file {relative!r}.")
    path = (root / relative).resolve()
    if not path.is_file() or not path.is_relative_to(root.resolve()):
        raise NotFound(f"no file {relative!r}.")
    return path


def _page(name: str) -> FileResponse:
    path = WEB / name
    if not path.is_file():
        raise NotFound(f"page {name} is not installed (src/miss/web/{name}).")
    return FileResponse(path, media_type="text/html", headers={"Cache-Control": "no-cache"})


def _asset(path: Path) -> FileResponse:
    # no-cache: the browser revalidates (ETag), so an edited module is picked up at once.
    return FileResponse(
        path, media_type=TYPES.get(path.suffix.lower()), headers={"Cache-Control": "no-cache"}
    )


def _login_first(request: Request) -> RedirectResponse:
    target = request.url.path + (f"?{request.url.query}" if request.url.query else "")
    return RedirectResponse(f"/login?next={quote(safe_next(target), safe='')}", status_code=303)


def safe_next(target: str) -> str:
    """``target`` if it is a path on this server, else "/". Browsers take ``//host``,
    ``/\\host`` and ``/<tab>/host`` for another host: after one "/" must come neither
    "/" nor "\\", and no control character, space or backslash may appear anywhere
    (the login page's script applies the same rule)."""
    if not re.match(r"/(?![/\\])", target) or re.search(r"[\x00-\x20\x7f-\xa0\\\\]", target):
        return "/"
    return target


@router.get("/login", response_model=None)
def login_page(request: Request) -> Response:
    """The login page; a ``next`` that leads off this server is replaced by "/"."""
    wanted = request.query_params.get("next")
    if wanted is not None and safe_next(wanted) != wanted:
        return RedirectResponse("/login?next=%2F", status_code=303)
    return _page("login.html")


@router.get("/docs")
def swagger_page() -> FileResponse:
    """Swagger UI for /openapi.json, from npm and served here (no CDN)."""
    return _page("docs.html")


@router.get("/redoc")
def redoc_page() -> FileResponse:
    """ReDoc for /openapi.json, from npm and served here (no CDN)."""
    return _page("redoc.html")


@router.get("/")
def library_page(request: Request, store: StoreDep) -> Response:
    return _page("index.html") if page_user(request, store) else _login_first(request)


@router.get("/volumes/{volume_id}")
def volume_page(volume_id: str, request: Request, store: StoreDep) -> Response:
    return _page("volume.html") if page_user(request, store) else _login_first(request)


@router.get("/models/{model_id}")
def viewer_page(model_id: str, request: Request, store: StoreDep) -> Response:
    """The viewer; opening it is a "view" in the audit log (when the model is yours)."""
    user = page_user(request, store)
    if user is None:
        return _login_first(request)
    _audit_view(store, request, user, model_id)
    return _page("model.html")


def _audit_view(store: Store, request: Request, user: User, model_id: str) -> None:
    try:
        visible_model(store, user, model_id)
    except NotFound:
        return  # the page will say so; nothing was viewed
    audit.record(store, "view", user.name, model_id, audit.address(request))


@router.get("/static/{path:path}")
def static_file(path: str) -> FileResponse:
    return _asset(safe_file(WEB, path))


@router.get("/vendor/{package}/{path:path}")
def vendor_file(package: str, path: str) -> FileResponse:
    """A file of three.js, Swagger UI or ReDoc, installed from npm by ``make``."""
    root = VENDOR.get(package)
    if root is None:
        raise NotFound(f"no package {package!r} is served.")
    if not root.is_dir():
        raise NotFound(f"{package} is not installed; run `make` (npm install in src/miss/web).")
    return _asset(safe_file(root, path, forbid=()))
