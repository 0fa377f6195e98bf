"""The browser pages and their files: the library, a volume, the viewer; static JS/CSS;
three.js from ``web/node_modules`` (installed by ``make`` from npm, served locally)."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse

import miss
from miss.server.errors import NotFound

WEB = Path(miss.__file__).parent / "web"
THREE = WEB / "node_modules" / "three"
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


@router.get("/")
def library_page() -> FileResponse:
    return _page("index.html")


@router.get("/volumes/{volume_id}")
def volume_page(volume_id: str) -> FileResponse:
    return _page("volume.html")


@router.get("/models/{model_id}")
def viewer_page(model_id: str) -> FileResponse:
    return _page("viewer.html")


@router.get("/static/{path:path}")
def static_file(path: str) -> FileResponse:
    return _asset(safe_file(WEB, path))


@router.get("/vendor/three/{path:path}")
def three_file(path: str) -> FileResponse:
    if not THREE.is_dir():
        raise NotFound("three.js is not installed; run `make` (npm install in src/miss/web).")
    return _asset(safe_file(THREE, path, forbid=()))
