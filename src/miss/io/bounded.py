"""Reading a volume within a memory budget: ``load_within(path)``.

A volume whose voxels fit the budget (:func:`miss.types.memory_budget`,
``MISS_IN_MEMORY_MAX_MB``) is read whole, as :func:`miss.io.load_volume` reads it. A
larger one that its reader can give plane by plane (a plain NIfTI-1 file, gzipped or
not, inflated as it is read; a folder of DICOM slices: :func:`miss.io.stream_volume`) is
written plane by plane to a chunked, compressed Zarr array in a temporary folder
(:func:`miss.server.storage.chunked.write_planes`, the server's own storage: one layer
of 64 planes is buffered) and handed on lazily, so that the job reads and meshes it block
by block (:mod:`miss.surface.blockwise`). The folder goes when the array does (or when
the process ends). Other formats are read whole whatever their size.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import weakref
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from miss.errors import DiskFull, MissError
from miss.io import load_volume, stream_volume
from miss.io.common import NotStreamable, Streamed
from miss.types import Volume, memory_budget

#: The Zarr array's name inside its temporary folder.
DATA = "data.zarr"


def load_within(
    path: str | os.PathLike[str], series: str | None = None, budget: int | None = None
) -> Volume:
    """:func:`miss.io.load_volume`, but a volume of more than ``budget`` bytes of voxels
    (default :func:`miss.types.memory_budget`) that its reader streams comes as a lazy
    array on disk (see the module docstring), never whole in memory. The same voxels,
    affine, metadata and patient either way."""
    limit = memory_budget() if budget is None else budget
    try:
        streamed = stream_volume(path, series)
    except MissError:  # a file load_volume refuses: let it say why, in its words
        streamed = None
    if streamed is None or voxel_bytes(streamed) <= limit:
        return load_volume(path, series)
    try:
        return spooled(streamed)
    except NotStreamable:  # NaN voxels become the minimum, which only a whole read knows
        return load_volume(path, series)


def voxel_bytes(streamed: Streamed) -> int:
    """Bytes the volume's voxels take in memory."""
    x, y, z = streamed.dims
    return x * y * z * np.dtype(streamed.dtype).itemsize


class _Span:
    """The smallest and largest value of the planes that pass through :meth:`watch`."""

    def __init__(self) -> None:
        self.lo, self.hi = np.inf, -np.inf

    def watch(self, planes: Iterator[np.ndarray]) -> Iterator[np.ndarray]:
        for plane in planes:
            self.lo, self.hi = min(self.lo, float(plane.min())), max(self.hi, float(plane.max()))
            yield plane


def spooled(streamed: Streamed, folder: Path | None = None) -> Volume:
    """The streamed volume written to a Zarr array in ``folder`` (default: a new
    temporary folder, removed with the array), as a Volume whose data is that array read
    lazily."""
    from miss.server.storage import chunked

    where = Path(tempfile.mkdtemp(prefix="miss-volume-")) if folder is None else folder
    span = _Span()
    try:
        attributes = {"affine": streamed.affine.tolist()}
        chunked.write_planes(
            where / DATA, streamed.dims, streamed.dtype, span.watch(streamed.planes),
            attributes, durable=False,
        )  # fmt: skip
        voxels, _, _ = chunked.open_array(where / DATA)
    except BaseException as exc:  # a full disk, a bad slice: no folder stays behind
        if folder is None:
            shutil.rmtree(where, ignore_errors=True)
        if isinstance(exc, DiskFull):  # its message names the server's data folder
            raise DiskFull(
                f"disk full: {where.parent} ran out of space while the volume was written "
                "there to be read block by block; free space there, set TMPDIR to a larger "
                "disk, or raise MISS_IN_MEMORY_MAX_MB to read it whole."
            ) from None
        raise
    if folder is None:
        weakref.finalize(voxels, shutil.rmtree, where, True)
    meta = streamed.meta(span.lo, span.hi)
    # a lazy (X, Y, Z) array: Volume's data is typed as the numpy array it mostly is
    return Volume(voxels, streamed.affine, meta=meta, patient=streamed.patient)  # type: ignore[arg-type]
