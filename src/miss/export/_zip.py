"""Scenes for one-mesh formats (STL, PLY, OBJ + MTL): a zip of files and a manifest.

STL and PLY hold one mesh without colour, and an OBJ needs its ``.mtl`` beside
it, but a writer returns one bytes object; so a scene in these formats is a zip.
Every such zip holds ``scene.json`` (title, provenance, and per part its file,
name, label, sRGB colour, opacity, triangles, mL and cm²) so the colours survive.

The zip is byte-for-byte reproducible: fixed timestamps (1980-01-01, the format's
epoch), fixed permissions, deflate at zlib's default level, entries in part order.
"""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Callable

from miss.scene import Scene, safe_names

MIME = "application/zip"
_EPOCH = (1980, 1, 1, 0, 0, 0)


def zip_files(files: list[tuple[str, bytes]]) -> bytes:
    """A deterministic zip of ``(name, data)`` entries, in order."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, data in files:
            info = zipfile.ZipInfo(name, date_time=_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16  # -rw-r--r-- when unpacked on Unix
            archive.writestr(info, data)
    return buffer.getvalue()


def manifest(
    scene: Scene, files: list[str], title: str | None, metadata: dict[str, str] | None
) -> bytes:
    """``scene.json``: the scene's title, provenance and one entry per part (with its file)."""
    parts = [
        {"file": name, **part.summary()} for name, part in zip(files, scene.parts, strict=True)
    ]
    document = {
        "title": title or scene.title,
        "units": "mm; axes patient LPS (+x left, +y posterior, +z superior)",
        "provenance": {str(k): str(v) for k, v in (metadata or {}).items()},
        "parts": parts,
    }
    return (json.dumps(document, indent=1) + "\n").encode("utf-8")


def zip_parts(
    scene: Scene,
    write: Callable[..., bytes],
    extension: str,
    title: str | None,
    metadata: dict[str, str] | None,
) -> bytes:
    """One file per part (``01_liver.stl`` ...) written by ``write``, plus ``scene.json``."""
    width = len(str(len(scene.parts)))
    names = [
        f"{i + 1:0{width}d}_{safe}.{extension}"
        for i, safe in enumerate(safe_names(scene.parts, style="file"))
    ]
    files = [
        (name, write(part.mesh, title=part.name, metadata=metadata))
        for name, part in zip(names, scene.parts, strict=True)
    ]
    return zip_files([*files, ("scene.json", manifest(scene, names, title, metadata))])
