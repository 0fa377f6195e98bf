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
#: Version of the internal form's layout (2: faces through meshoptimizer's index codec,
#: normals as their XOR with the computed ones; version 1's files are read too).
VERSION = 2


@dataclass(frozen=True)
class Stored:
    """What a job encoded: the scene and the title and provenance it passed the writers."""

    scene: Scene
    title: str | None
    metadata: dict[str, str]


def scene_bytes(scene: Scene, title: str | None, metadata: dict[str, str]) -> bytes:
    """``scene`` as an .npz, every array given back bit for bit in its own dtype.

    Per part ``v<i>`` (N, 3) vertices in mm, ``f<i>`` its faces, ``n<i>`` normals and
    ``l<i>`` face labels where the part has them; ``header`` the JSON of everything else
    (floats round-trip exactly). Deflated at zlib's fastest level, and:

    - faces through meshoptimizer's index codec (a job's scene is in vertex-cache order,
      :func:`miss.geometry.locality_order`: about 1 byte a triangle, a fifth of the list
      deflated), with ``r<i>``, how far the codec turned each triangle, to turn it back;
      plain where the codec would not give them back;
    - normals that are the area-weighted ones of the faces (what the pipeline gives) not
      at all, made again on reading; float32 ones that differ by a few bits as their XOR
      with those; others as they are.
    """
    arrays: dict[str, np.ndarray] = {}
    parts = []
    for i, part in enumerate(scene.parts):
        mesh = part.mesh
        arrays[f"v{i}"] = mesh.vertices
        faces = _encoded_faces(mesh.faces, mesh.n_vertices)
        if faces is None:
            arrays[f"f{i}"] = mesh.faces
        else:
            arrays[f"f{i}"], arrays[f"r{i}"] = faces
        normals, stored = _normals(mesh)
        if stored is not None:
            arrays[f"n{i}"] = stored
        if mesh.labels is not None:
            arrays[f"l{i}"] = mesh.labels
        parts.append({"name": part.name, "color": list(part.color), "opacity": part.opacity,
                      "label": part.label, "normals": normals,
                      "faces": "plain" if faces is None else "meshopt",
                      "faces_dtype": mesh.faces.dtype.str})  # fmt: skip
    header = {"version": VERSION, "title": title, "metadata": metadata, "parts": parts,
              "scene_title": scene.title, "notes": list(scene.notes)}  # fmt: skip
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as archive:
        for name, array in arrays.items():  # as numpy.savez lays out an .npz
            with archive.open(f"{name}.npy", "w", force_zip64=True) as entry:
                np.lib.format.write_array(entry, np.asanyarray(array), allow_pickle=False)
    return buffer.getvalue()


#: meshoptimizer's index codec version written (its decoders read every version).
_INDEX_CODEC = 1
#: The turns of a triangle: its vertices' order after ``np.roll(face, -turn)``.
_TURNS = (0, 1, 2)


def _encoded_faces(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray] | None:
    """``faces`` through meshoptimizer's index codec and each triangle's turn (uint8) that
    gives it back from the decoded one; None when that would not be exact (faces not
    integers in [0, 2^32), or the codec gave a triangle that is no turn of its own)."""
    import meshoptimizer

    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0 or faces.dtype.kind not in "iu":
        return None
    if int(faces.min()) < 0 or int(faces.max()) >= min(n_vertices, 2**32):
        return None
    indices = np.ascontiguousarray(faces, dtype=np.uint32).ravel()
    meshoptimizer.encode_index_version(_INDEX_CODEC)
    encoded = np.frombuffer(
        meshoptimizer.encode_index_buffer(indices, len(indices)), dtype=np.uint8
    )
    decoded = _decoded_faces(encoded, len(faces))
    turns = np.full(len(faces), 255, dtype=np.uint8)
    for turn in reversed(_TURNS):  # the smallest turn that fits wins
        turns[(np.roll(decoded, -turn, axis=1) == faces).all(axis=1)] = turn
    return None if (turns == 255).any() else (encoded, turns)


def _decoded_faces(encoded: np.ndarray, count: int) -> np.ndarray:
    import meshoptimizer

    data = meshoptimizer.decode_index_buffer(count * 3, 4, encoded.tobytes())
    return np.asarray(data).view(np.uint32).reshape(-1, 3)


def _normals(mesh: Mesh) -> tuple[str | None, np.ndarray | None]:
    """How the normals are kept and the array stored for them: (None, None) the mesh has
    none; ("computed", None) they are its faces' area-weighted normals, made again on
    reading; ("xor", bits) float32 ones as their bits' XOR with those; ("stored", them)."""
    if mesh.normals is None:
        return None, None
    again = vertex_normals(mesh.vertices, mesh.faces)
    if again.dtype != mesh.normals.dtype or again.shape != mesh.normals.shape:
        return "stored", mesh.normals
    if np.array_equal(again, mesh.normals):
        return "computed", None
    return "xor", again.view(np.uint32) ^ np.ascontiguousarray(mesh.normals).view(np.uint32)


def read_scene(path: Path) -> Stored:
    """The scene, title and provenance :func:`scene_bytes` stored at ``path`` (this
    layout's and the first's, version 1)."""
    with np.load(path, allow_pickle=False) as stored:
        header = json.loads(stored["header"].tobytes())
        parts = tuple(
            Part(
                entry["name"],
                _mesh(stored, i, entry),
                tuple(entry["color"]),
                entry["opacity"],
                entry["label"],
            )  # fmt: skip
            for i, entry in enumerate(header["parts"])
        )
    scene = Scene(parts, header["scene_title"], tuple(header["notes"]))
    return Stored(scene, header["title"], header["metadata"])


def _mesh(stored: Any, i: int, entry: dict[str, Any]) -> Mesh:
    vertices = stored[f"v{i}"]
    if entry.get("faces", "plain") == "meshopt":
        turns = stored[f"r{i}"]  # each access inflates the entry again: once
        decoded = _decoded_faces(stored[f"f{i}"], len(turns))
        faces = np.empty_like(decoded)
        for turn in _TURNS:
            mine = turns == turn
            faces[mine] = np.roll(decoded[mine], -turn, axis=1)
        faces = faces.astype(np.dtype(entry["faces_dtype"]))
    else:
        faces = stored[f"f{i}"]
    labels = stored[f"l{i}"] if f"l{i}" in stored.files else None
    kind = entry["normals"]
    if kind in ("computed", "xor"):
        normals = vertex_normals(vertices, faces)
        if kind == "xor":
            normals = (normals.view(np.uint32) ^ stored[f"n{i}"]).view(np.float32)
        return Mesh(vertices, faces, normals, labels)
    return Mesh(vertices, faces, stored[f"n{i}"] if kind else None, labels)


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
