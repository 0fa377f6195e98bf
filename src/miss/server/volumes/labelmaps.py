"""A label map laid over a stored volume (e.g. TotalSegmentator output).

Stored beside the volume as ``volumes/<id>/labels.zarr`` (the map's own voxels, (X, Y, Z),
chunked: :mod:`miss.server.storage.chunked`) and ``labels.json`` (its affine, the labels with voxel counts, names and
colours, and a hash that enters the cache key of jobs built on it). The pipeline resamples
it onto the volume's grid in patient mm when a job asks for ``labels``.
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from miss.errors import BadParameter, MissError
from miss.io.confined import Confinement, Limits, parse_upload
from miss.server.storage import chunked
from miss.server.storage.store import Store, write_atomic
from miss.server.volumes import imaging
from miss.server.volumes.ingest import source_hash
from miss.structures.labelmap import align_labels, label_counts
from miss.structures.labels import LabelInfo, LabelTable, describe
from miss.types import Volume

DATA, INFO = "labels.zarr", "labels.json"
#: Where an older MISS kept the voxels (``Store.init`` migrates them).
OLD_DATA = "labels.npy"


def read_labelmap(
    path: Path, volume: Volume, work: Path, reading: tuple[Confinement, Limits]
) -> tuple[Volume, dict[str, Any]]:
    """Read an uploaded label map (confined, like every upload) and the label table that
    comes with it; refuse a non-label volume or one that misses ``volume``."""
    try:
        parsed = parse_upload(work, path.name, *reading, mode="labels")
    except MissError as exc:  # the server's folders are none of the client's business
        raise type(exc)(str(exc).replace(f"{work}/", "")) from None
    assert parsed.volume is not None
    labels = parsed.volume
    counts = label_counts(labels)
    if counts is None:
        raise BadParameter(
            f"{path.name} is not a label map: it needs whole numbers 0..65535 "
            f"(0 = background) with few distinct values; it holds {labels.data.dtype} data."
        )
    if not counts:
        raise BadParameter(f"{path.name} holds no labels (every voxel is 0, the background).")
    align_labels(labels, volume)  # raises BadParameter when the two do not overlap in mm
    return labels, _meta(labels, counts, _table(parsed.table), parsed.table_source)


def read_segmentation(
    path: Path, volume: Volume, work: Path, reading: tuple[Confinement, Limits]
) -> tuple[Volume, dict[str, Any]]:
    """Read a DICOM SEG or RT-STRUCT (confined) as a label map over ``volume``.

    Parameters
    ----------
    path : Path
        The segmentation file directly inside ``work``, or the folder ``work/unzipped``
        of files among which is exactly one SEG or RT-STRUCT (e.g. a series fetched from
        the PACS).
    volume : Volume
        The stored image volume: an RT-STRUCT is rasterised on its grid (affine, dims), a
        SEG keeps its own grid and must overlap it in patient mm.
    work : Path
        The job's working folder (the confined child may write only there).

    Returns
    -------
    labels, meta
        As :func:`read_labelmap`: ``meta["labels"]`` names and colours each label from
        the file, ``meta["table"]`` is ``"DICOM SEG"`` or ``"RT-STRUCT"``; store both
        with :func:`save`.
    """
    if path.is_dir() and path != work / "unzipped":
        raise ValueError(f"put the files in {work / 'unzipped'}, not {path}")
    upload = path.name if path.is_file() else ".segmentation"  # none: read unzipped/
    grid = {"affine": volume.affine.tolist(), "dims": list(volume.dims)}
    try:
        parsed = parse_upload(work, upload, *reading, mode="segmentation", grid=grid)
    except MissError as exc:  # the server's folders are none of the client's business
        raise type(exc)(str(exc).replace(f"{work}/", "")) from None
    assert parsed.volume is not None
    labels = parsed.volume
    counts = label_counts(labels)
    if not counts:  # the readers refuse an empty map; this guards the child's answer
        raise BadParameter(f"{path.name} holds no labelled voxels.")
    align_labels(labels, volume)  # raises BadParameter when the two do not overlap in mm
    return labels, _meta(labels, counts, _table(parsed.table), parsed.table_source)


def _meta(labels: Volume, counts: dict[int, int], table: LabelTable, source: str) -> dict[str, Any]:
    """``labels.json``: the map's grid, its labels (count, name, colour), where the names
    came from, and the hash jobs key their cache on."""
    entries = []
    for label, voxels in sorted(counts.items()):
        info = describe(label, table)
        entries.append(
            {"label": label, "name": info.name, "voxels": voxels, "color": list(info.color or ())}
        )
    return {
        "affine": labels.affine.tolist(),
        "dims": list(labels.dims),
        "labels": entries,
        "table": source,
        "sha256": source_hash(labels.data, labels.affine),
    }


def _table(rows: list[dict[str, Any]]) -> LabelTable:
    """The label table the confined reader found, checked row by row (bad rows dropped)."""
    table: LabelTable = {}
    for row in rows:
        try:
            color = tuple(float(c) for c in row.get("color") or ())
            table[int(row["label"])] = LabelInfo(
                str(row.get("name", ""))[:200],
                color if len(color) == 3 else None,
                float(row.get("opacity", 1.0)),
            )
        except (KeyError, TypeError, ValueError):
            continue
    return table


def save(store: Store, volume_id: str, labels: Volume, meta: dict[str, Any]) -> None:
    """Write both; ``labels.json`` last, so it only names a complete ``labels.zarr``."""
    folder = store.volume_dir(volume_id)
    (folder / INFO).unlink(missing_ok=True)  # the old map is gone before its voxels change
    shutil.rmtree(folder / DATA, ignore_errors=True)
    provenance = {"source_sha256": meta["sha256"], "table": meta.get("table", "")}
    chunked.write_array(
        folder / DATA, labels.data, {"affine": labels.affine, "provenance": provenance}
    )
    write_atomic(folder / INFO, json.dumps(meta).encode())


def info(store: Store, volume_id: str) -> dict[str, Any] | None:
    """``labels.json`` of the volume, or None when it has no label map."""
    path = store.volume_dir(volume_id) / INFO
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        return None


def remove(store: Store, volume_id: str) -> bool:
    """Delete the label map; False when there was none."""
    folder = store.volume_dir(volume_id)
    existed = (folder / INFO).exists()
    (folder / INFO).unlink(missing_ok=True)  # first: the map is gone as soon as this is
    shutil.rmtree(folder / DATA, ignore_errors=True)
    (folder / OLD_DATA).unlink(missing_ok=True)
    return existed


def load(store: Store, volume_id: str) -> tuple[Volume, LabelTable] | None:
    """The stored map (``Store.voxels``) and its table, for a job; None when there is none."""
    meta = info(store, volume_id)
    if meta is None:
        return None
    folder = store.volume_dir(volume_id)
    data = store.voxels(folder / DATA, folder / OLD_DATA)
    table = {
        e["label"]: LabelInfo(e["name"], tuple(e["color"]) if e.get("color") else None)
        for e in meta["labels"]
    }
    return Volume(data=data, affine=np.array(meta["affine"]), meta={}), table


def public(meta: dict[str, Any] | None) -> dict[str, Any] | None:
    """What ``GET /api/volumes/{id}`` shows of a label map."""
    if meta is None:
        return None
    return {
        "labels": [{k: e[k] for k in ("label", "name", "voxels", "color")} for e in meta["labels"]],
        "table": meta.get("table", ""),
        # names this map in slice URLs, so a browser never shows a replaced map's colours
        "sha256": meta.get("sha256", ""),
    }


def cache_key(spec_key: str, meta: dict[str, Any] | None) -> str:
    """A job's key: a labels job also depends on which map it reads."""
    if meta is None:
        return spec_key
    return hashlib.sha256(f"{spec_key}:{meta['sha256']}".encode()).hexdigest()[:32]


def labels_at(
    store: Store, volume_id: str, affine: np.ndarray, ijk: np.ndarray
) -> np.ndarray | None:
    """The label map's labels at volume voxels, nearest neighbour in patient mm.

    Parameters
    ----------
    affine : (4, 4) float array
        The volume's voxel-to-patient (mm) affine.
    ijk : (3, N) int array
        Voxel indices of the volume (0-based).

    Returns
    -------
    (N,) int64 array, 0 outside the map; None when the volume has no label map.
    """
    meta = info(store, volume_id)
    if meta is None:
        return None
    folder = store.volume_dir(volume_id)
    data = store.voxels(folder / DATA, folder / OLD_DATA, lazy=True)
    to_labels = np.linalg.inv(np.asarray(meta["affine"])) @ affine  # volume index -> map index
    where = np.rint(to_labels[:3, :3] @ ijk + to_labels[:3, 3:4]).astype(np.int64)
    inside = np.all((where >= 0) & (where < np.asarray(data.shape)[:, None]), axis=0)
    out = np.zeros(ijk.shape[1], dtype=np.int64)
    if not inside.any():
        return out
    hit = where[:, inside]
    lo, hi = hit.min(axis=1), hit.max(axis=1) + 1
    # only the box the points fall in is read: one plane when both share a grid
    block = np.asarray(data[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]])
    out[inside] = block[tuple(hit - lo[:, None])]
    return out


def colours(store: Store, volume_id: str) -> dict[int, tuple[float, float, float]]:
    """Each label's sRGB colour (fractions), the one its part gets in a model."""
    meta = info(store, volume_id) or {"labels": []}
    return {e["label"]: tuple(e["color"]) for e in meta["labels"] if len(e.get("color") or ()) == 3}


#: Opacity of a label's colour laid over a slice: the grey beneath still reads.
OVERLAY_ALPHA = 0.45


def slice_overlay(
    store: Store, volume_id: str, affine: np.ndarray, dims: tuple[int, int, int],
    view: dict[str, Any], index: int,
) -> np.ndarray | None:  # fmt: skip
    """The label map's colours over one slice of the volume (``imaging.slice_plane``'s
    view and index), in display orientation.

    Returns
    -------
    (rows, columns, 4) float32 array, RGB 0-255 and alpha (0 where no label); None when
    the volume has no label map.
    """
    fixed = view["axis"]
    axes = [slice(0, n) for n in dims]
    axes[fixed] = slice(index, index + 1)
    grid = np.mgrid[tuple(axes)]  # (3, X, Y, Z) with the fixed axis one long
    found = labels_at(store, volume_id, affine, grid.reshape(3, -1))
    if found is None:
        return None
    labels = imaging.slice_plane(found.reshape(grid.shape[1:]), view, 0)
    rgba = np.zeros((*labels.shape, 4), dtype=np.float32)
    table = colours(store, volume_id)
    for label in np.unique(labels):
        if label:
            rgb = 255.0 * np.asarray(table.get(int(label), (1.0, 1.0, 0.0)))
            rgba[labels == label] = (*rgb, OVERLAY_ALPHA)
    return rgba
