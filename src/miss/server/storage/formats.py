"""Formats when asked: a job keeps what viewing needs, every other format is made on the
first download and kept in a bounded cache.

A server job writes the compressed GLB (with its preview and levels of detail) and the
scene it encoded, in one compact internal form: ``model.mesh.npz`` (each part's arrays in
the dtypes the pipeline gave them, deflated fast, and a JSON header with the title,
provenance, names, colours and opacities the writers take). STL, PLY, OBJ, VRML, WRZ,
X3D, 3MF and the plain GLB (every writer of :data:`miss.export.WRITERS` but the GLB) are
made from it by the same writers, so their bytes are those a job would have written; the first download
writes ``model.<fmt>`` atomically beside it, later ones read that file.

One writer at a time per (model, format), across server processes too: an exclusive
``fcntl.flock`` on ``.<fmt>.lock`` in the model's folder; a download asked meanwhile
waits for it and reads the file it made. Each make appends a line to ``made.log`` there.

The made files are a cache of at most ``MISS_FORMAT_CACHE_MB`` (0: no cap) over every
model: once a make takes it over, the made files least recently downloaded (their
modification time, touched on each download) are removed first, never the GLB, the
levels of detail, the preview or the internal form. A model's made files are in its
folder, so they go with it, and the account's quota counts them.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import io
import json
import os
import time
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np

from miss.errors import is_disk_full
from miss.export import FORMATS, WRITERS, export
from miss.geometry import vertex_normals
from miss.scene import Part, Scene
from miss.server.core.errors import DiskFull, NotFound
from miss.server.storage.db import ModelRow
from miss.server.storage.store import Store, write_atomic
from miss.types import Mesh

#: The internal form of a model's scene (``model.*``: a failed job's cleanup removes it).
MESH_FILE = "model.mesh.npz"
#: One line per format made on request, in the model's folder.
MADE_LOG = "made.log"
#: Formats a job writes itself: what the viewer draws.
KEPT = ("glb",)
#: Formats made from the internal form on their first download.
ON_REQUEST = tuple(fmt for fmt in FORMATS if fmt not in KEPT)
#: Version of the internal form's layout.
VERSION = 1


@dataclass(frozen=True)
class Stored:
    """What a job encoded: the scene and the title and provenance it passed the writers."""

    scene: Scene
    title: str | None
    metadata: dict[str, str]


def scene_bytes(scene: Scene, title: str | None, metadata: dict[str, str]) -> bytes:
    """``scene`` as an .npz: ``v<i>`` (N, 3) vertices in mm, ``f<i>`` (F, 3) faces,
    ``n<i>`` normals and ``l<i>`` face labels where the part has them, in their own dtypes;
    ``header`` the JSON of everything else (floats round-trip exactly). Normals that are
    the area-weighted ones of the faces (what the pipeline gives) are not stored but made
    again on reading, bit for bit: a third less to keep. Deflated at zlib's fastest level:
    half the bytes for about 0.3 s a million triangles."""
    arrays: dict[str, np.ndarray] = {}
    parts = []
    for i, part in enumerate(scene.parts):
        mesh = part.mesh
        arrays[f"v{i}"], arrays[f"f{i}"] = mesh.vertices, mesh.faces
        normals = _normals_kind(mesh)
        if normals == "stored" and mesh.normals is not None:
            arrays[f"n{i}"] = mesh.normals
        if mesh.labels is not None:
            arrays[f"l{i}"] = mesh.labels
        parts.append({"name": part.name, "color": list(part.color), "opacity": part.opacity,
                      "label": part.label, "normals": normals})  # fmt: skip
    header = {"version": VERSION, "title": title, "metadata": metadata, "parts": parts,
              "scene_title": scene.title, "notes": list(scene.notes)}  # fmt: skip
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for name, array in arrays.items():  # as numpy.savez lays out an .npz
            with archive.open(f"{name}.npy", "w", force_zip64=True) as entry:
                np.lib.format.write_array(entry, np.asanyarray(array), allow_pickle=False)
    return buffer.getvalue()


def _normals_kind(mesh: Mesh) -> str | None:
    """None: the mesh has none; "computed": they are its faces' area-weighted normals, made
    again on reading; "stored": other ones, kept."""
    if mesh.normals is None:
        return None
    again = vertex_normals(mesh.vertices, mesh.faces)
    same = again.dtype == mesh.normals.dtype and np.array_equal(again, mesh.normals)
    return "computed" if same else "stored"


def read_scene(path: Path) -> Stored:
    """The scene, title and provenance :func:`scene_bytes` stored at ``path``."""
    with np.load(path, allow_pickle=False) as stored:
        header = json.loads(stored["header"].tobytes())
        parts = tuple(
            Part(
                entry["name"],
                _mesh(stored, i, entry["normals"]),
                tuple(entry["color"]),
                entry["opacity"],
                entry["label"],
            )  # fmt: skip
            for i, entry in enumerate(header["parts"])
        )
    scene = Scene(parts, header["scene_title"], tuple(header["notes"]))
    return Stored(scene, header["title"], header["metadata"])


def _mesh(stored: Any, i: int, normals: str | None) -> Mesh:
    vertices, faces = stored[f"v{i}"], stored[f"f{i}"]
    labels = stored[f"l{i}"] if f"l{i}" in stored.files else None
    if normals == "computed":
        return Mesh(vertices, faces, vertex_normals(vertices, faces), labels)
    return Mesh(vertices, faces, stored[f"n{i}"] if normals else None, labels)


def entries(scene: Scene) -> dict[str, dict[str, Any]]:
    """The model's ``files`` entries of the formats made on request, before they are:
    their type, no bytes nor ETag yet (:func:`record` fills them in once made)."""
    del scene  # every format holds any scene in one file of its own type
    return {
        fmt: {"bytes": None, "etag": None, "mime": WRITERS[fmt].mime, "on_request": True}
        for fmt in ON_REQUEST
    }


def describe(data: bytes) -> dict[str, Any]:
    """A file's ``files`` entry fields: its size and ETag (as the job's files have them)."""
    return {"bytes": len(data), "etag": hashlib.sha256(data).hexdigest()[:32]}


class Busy(Exception):
    """Another holder has the lock :func:`locked` was asked not to wait for."""


@contextlib.contextmanager
def locked(path: Path, wait: bool = True) -> Iterator[None]:
    """Hold an exclusive ``flock`` on ``path`` (made if missing, never its folder): one
    holder at a time across threads and processes (each opens its own description).
    ``wait=False`` raises :class:`Busy` rather than wait for another holder."""
    try:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    except FileNotFoundError:
        raise NotFound(f"model {path.parent.name} was deleted meanwhile.") from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        except BlockingIOError:
            raise Busy(path) from None
        yield
    finally:
        os.close(fd)  # releases the lock


def read(folder: Path, fmt: str, cap: int) -> bytes:
    """The bytes of ``folder``'s ``model.<fmt>``, made first if need be (:func:`ensure`),
    read under its lock: no eviction removes it meanwhile."""
    while True:
        path, _ = ensure(folder, fmt, cap)
        with locked(_lock_of(path)), contextlib.suppress(FileNotFoundError):
            return path.read_bytes()


def disk_full(fmt: str) -> DiskFull:
    """The 507 of a format that did not fit on the disk."""
    return DiskFull(
        f"disk full: the server's data folder ran out of space while making this model's "
        f".{fmt} file, and nothing of it was kept; ask the administrator to free space there "
        "(or to lower MISS_FORMAT_CACHE_MB, the room kept for formats made on request), "
        "then download it again."
    )


def ensure(folder: Path, fmt: str, cap: int) -> tuple[Path, dict[str, Any] | None]:
    """``folder``'s ``model.<fmt>``, made from its internal form unless it is there: its
    path, and its ``files`` fields (:func:`describe`) when this call made it (None: it
    was there; its modification time is touched, the cache's record of its use).
    ``cap``: bytes of made files kept over all models (:func:`evict`; 0: no cap).
    Raises ``DiskFull`` (507, nothing left behind) when the disk is full."""
    path = folder / f"model.{fmt}"
    with locked(_lock_of(path)):
        if path.is_file() and not _zipped_scene(path, fmt):
            os.utime(path)
            return path, None
        start = time.perf_counter()
        try:
            stored = read_scene(folder / MESH_FILE)
        except FileNotFoundError:
            raise NotFound(
                f"the stored mesh of model {folder.name} is missing, so its .{fmt} file cannot "
                "be made; delete the model and submit it again."
            ) from None
        data = export(stored.scene, fmt, title=stored.title, metadata=stored.metadata)
        try:
            write_atomic(path, data)
        except OSError as exc:
            if is_disk_full(exc):
                raise disk_full(fmt) from None
            raise
        _log(folder, fmt, len(data), time.perf_counter() - start)
    if cap > 0:
        evict(folder.parent, cap, keep=path)
    return path, describe(data)


def _zipped_scene(path: Path, fmt: str) -> bool:
    """True for an STL, PLY or OBJ made before they held a scene in one file (a zip of
    one file per part, which other tools cannot open): it is made again."""
    if not WRITERS[fmt].one_mesh:
        return False
    with open(path, "rb") as made:
        return made.read(4) == b"PK\x03\x04"


def _log(folder: Path, fmt: str, size: int, seconds: float) -> None:
    """One line in ``made.log`` (best effort: a full disk has the file in place already)."""
    when = datetime.now(UTC).isoformat(timespec="seconds")
    with contextlib.suppress(OSError), open(folder / MADE_LOG, "a") as log:
        log.write(f"{when} made {fmt}: {size} bytes in {seconds:.2f} s, pid {os.getpid()}\n")


def made_files(models: Path) -> list[tuple[int, int, Path]]:
    """(modification time ns, bytes, path) of every made file under ``models`` (the
    folders with an internal form: an older model's files are its only copy)."""
    found = []
    for folder in models.iterdir():
        if not (folder / MESH_FILE).is_file():
            continue
        for fmt in ON_REQUEST:
            path = folder / f"model.{fmt}"
            with contextlib.suppress(OSError):  # not made, or removed meanwhile
                stat = path.stat()
                found.append((stat.st_mtime_ns, stat.st_size, path))
    return found


def evict(models: Path, cap: int, keep: Path | None = None) -> list[Path]:
    """Remove the least recently used made files under ``models`` until they take at
    most ``cap`` bytes (never ``keep``, the one just made); the removed paths."""
    found = sorted(made_files(models), key=lambda entry: entry[0])
    total = sum(size for _, size, _ in found)
    removed = []
    for _, size, path in found:
        if total <= cap:
            break
        if path == keep:
            continue
        # Not one being made or read under its lock; a download streaming it keeps its
        # open file.
        with contextlib.suppress(Busy, NotFound), locked(_lock_of(path), wait=False):
            path.unlink(missing_ok=True)
            removed.append(path)
            total -= size
    return removed


def record(store: Store, model_id: str, fmt: str, made: dict[str, Any]) -> dict[str, Any]:
    """Fill in ``fmt``'s bytes and ETag in the model's ``files`` once it is made (the same
    bytes every time it is made again: they stay true after it is evicted); the files."""
    with locked(store.model_dir(model_id) / ".files.lock"):  # one row update at a time
        with store.session() as s:  # afresh: another process may have made another format
            row = s.get(ModelRow, model_id)
        if row is None:
            raise NotFound(f"no model {model_id!r}; it was deleted meanwhile.")
        files = dict(row.files or {})
        if files.get(fmt, {}).get("etag") != made["etag"]:
            # the type too: a scene's STL, PLY and OBJ were listed as zips before
            files[fmt] = {**files.get(fmt, {}), **made, "mime": WRITERS[fmt].mime}
            store.update_model(model_id, files=files)
    return files


def _lock_of(path: Path) -> Path:
    """The lock file of a made file ``model.<fmt>``: ``.<fmt>.lock`` beside it (the whole
    format: ``model.plain.glb``'s is ``.plain.glb.lock``, not the GLB's)."""
    return path.with_name(f".{path.name.removeprefix('model.')}.lock")
