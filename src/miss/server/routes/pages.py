"""The browser pages and their files: the login, the library, a volume, the viewer;
static JS/CSS; three.js from ``web/node_modules`` (installed by ``make`` from npm, served
locally). Pages other than the login need a session; without one they redirect to it."""

from __future__ import annotations

from pathlib import Path
from urllib.parse import quote

from fastapi import APIRouter, Request
from fastapi.responses import FileResponse, RedirectResponse, Response

from miss.server import audit
from miss.server.accounts import User
from miss.server.core import assets
from miss.server.core.auth import page_user
from miss.server.core.deps import StoreDep, visible_model
from miss.server.core.errors import NotFound
from miss.server.core.nextpath import safe_next
from miss.server.storage.store import Store

WEB = assets.WEB

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


def _page(name: str, inline_styles: bool = False) -> Response:
    if not (WEB / name).is_file():
        raise NotFound(f"page {name} is not installed (src/miss/web/{name}).")
    return assets.page(name, inline_styles=inline_styles)


def _asset(path: Path, request: Request, version: str | None = None) -> Response:
    """``path`` as a static file: kept a year under the current ``version``
    (:mod:`miss.server.core.assets`), else ``no-cache`` (asked for each time, so an edited
    module is picked up at once), and a copy the browser holds already (its ETag in
    ``If-None-Match``) answered 304 without the file."""
    keep = version is not None and version == assets.version()
    cache = {"Cache-Control": assets.KEEP if keep else "no-cache"}
    response = FileResponse(
        path,
        media_type=TYPES.get(path.suffix.lower()),
        headers=cache,
        stat_result=path.stat(),  # its ETag now, not when it is sent
    )
    etag = response.headers["etag"]
    held = request.headers.get("if-none-match", "")
    if etag in (tag.strip().removeprefix("W/") for tag in held.split(",")):
        return Response(status_code=304, headers={"ETag": etag, **cache})
    return response


def _login_first(request: Request) -> RedirectResponse:
    target = request.url.path + (f"?{request.url.query}" if request.url.query else "")
    return RedirectResponse(f"/login?next={quote(safe_next(target), safe='')}", status_code=303)


@router.get("/login", response_model=None)
def login_page(request: Request) -> Response:
    """The login page. Its ``next`` is what ``safe_next`` makes of it (the page sends it
    back with the login, whose answer names the place to go): any other spelling is
    redirected to that one, "/" for a place off this server."""
    wanted = request.query_params.get("next")
    if wanted is not None and safe_next(wanted) != wanted:
        return RedirectResponse(f"/login?next={quote(safe_next(wanted), safe='')}", 303)
    return _page("login.html")


@router.get("/docs")
def swagger_page() -> Response:
    """Swagger UI for /openapi.json, from npm and served here (no CDN)."""
    return _page("docs.html")


@router.get("/redoc")
def redoc_page() -> Response:
    """ReDoc for /openapi.json, from npm and served here (no CDN)."""
    return _page("redoc.html", inline_styles=True)


@router.get("/")
def library_page(request: Request, store: StoreDep) -> Response:
    """The library page (volumes and models); to the login page first when not logged in."""
    return _page("index.html") if page_user(request, store) else _login_first(request)


@router.get("/volumes/{volume_id}")
def volume_page(volume_id: str, request: Request, store: StoreDep) -> Response:
    """A volume's page; to the login page first when not logged in."""
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
def static_file(path: str, request: Request) -> Response:
    """A file of the browser viewer (``src/miss/web``): its modules, styles and images; 404
    when there is none."""
    return _asset(safe_file(WEB, path), request)


@router.get("/vendor/{package}/{path:path}")
def vendor_file(package: str, path: str, request: Request) -> Response:
    """A file of three.js, Swagger UI or ReDoc, installed from npm by ``make``."""
    return _asset(_vendor(package, path), request)


@router.get("/v/{version}/static/{path:path}")
def versioned_static_file(version: str, path: str, request: Request) -> Response:
    """``/static/{path}`` as a page of that ``version`` asks for it (:mod:`..assets`)."""
    return _asset(safe_file(WEB, path), request, version)


@router.get("/v/{version}/vendor/{package}/{path:path}")
def versioned_vendor_file(version: str, package: str, path: str, request: Request) -> Response:
    """``/vendor/{package}/{path}`` as a page of that ``version`` asks for it."""
    return _asset(_vendor(package, path), request, version)


def _vendor(package: str, path: str) -> Path:
    if package not in assets.VENDOR:
        raise NotFound(f"no package {package!r} is served.")
    root = assets.VENDOR[package][0]
    if not root.is_dir():
        raise NotFound(f"{package} is not installed; run `make` (npm install in src/miss/web).")
    return safe_file(root, path, forbid=())
