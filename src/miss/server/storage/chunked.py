"""Stored voxels as chunked, compressed Zarr v3 arrays (``data.zarr``, ``labels.zarr``).

A volume's (X, Y, Z) voxels, in the dtype the reader gave, are stored as the Zarr
array (Z, Y, X) (``dimension_names``), cut into cubes of ``CHUNK`` voxels and compressed
with Blosc/zstd; the affine (voxel index to LPS mm) and the provenance are its
attributes. (Z, Y, X) in C order holds the bytes of (X, Y, Z) in Fortran order, the
order MISS's readers and jobs use: reading a volume whole is then one copy, its
transpose a free view (transposing it instead took 3-5 s for 200 MB, 4-6 x the read).
It is written from an iterator of (X, Y) planes, z in order, so no one ever holds the
whole volume: ``CHUNK[2]`` planes are buffered, then written as one slab.
:class:`Voxels` gives the stored array back as (X, Y, Z), read lazily.

Reading: ``zarr`` writes the arrays; MISS reads them itself, chunk by chunk from the
files (:meth:`Voxels.chunk`, Blosc's ``decompress``, the header's sizes checked first),
with zarr kept for the indexes it does not take (tested equal to zarr's on any basic
index). Through zarr each read crosses to its event loop's thread and back: a 64³ int16
chunk took 1.05 ms that way against 0.44 ms directly, and on 512 x 512 x 600 (2 shared
cores, loaded) a whole read 0.60 against 0.44 s, a sagittal / coronal / axial slice
63 / 61 / 46 against 45 / 43 / 36 ms.

Why 64 x 64 x 64: on a 512 x 512 x 300 int16 CT (measured with ``zarr`` 3.1, 2 cores)
one sagittal / coronal / axial slice reads in 24 / 22 / 36 ms and the whole volume in
0.20 s; 128 x 128 x 16 reads axial slices in 9 ms but sagittal in 43, 32^3 is 2-5 x
slower everywhere (more chunks), one chunk per axial plane takes 160 ms per sagittal
slice. Slice pages use all three planes, jobs read everything: cubes are the balance.

The files are written by MISS, but :func:`open_array` still checks their metadata
against what MISS writes (format, dimensions, dtype, chunking, codecs) before a byte of
voxels is read: a folder restored from elsewhere cannot ask for other codecs.
"""

from __future__ import annotations

import itertools
import json
import math
import os
import secrets
import shutil
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from miss.errors import DiskFull, UnreadableVolume, is_disk_full

if TYPE_CHECKING:
    from miss.surface.blocks import ChunkCache

#: Chunk shape, (X, Y, Z) voxels (see the module docstring for the measurements).
CHUNK = (64, 64, 64)
#: The stored array's axes: z slowest, x fastest (see the module docstring).
AXES = ("z", "y", "x")
#: The dtypes readers hand on (``miss.io.common``): real numbers, native little-endian.
DTYPES = frozenset(
    ["uint8", "int8", "uint16", "int16", "uint32", "int32", "int64", "uint64", "float32", "float64"]
)
#: The compressor, as zarr.json names it; the only one :func:`open_array` accepts.
BLOSC: dict[str, Any] = {"cname": "zstd", "clevel": 3, "shuffle": "bitshuffle"}
_MAX_CHUNK_SIDE = 1024
_BYTES = {"name": "bytes", "configuration": {"endian": "little"}}
_MAX_META_BYTES = 1 << 20
#: A read crossing at least this many chunks decompresses them on every core.
_PARALLEL_CHUNKS = 16
#: Suffix of a Zarr folder being written (``Store.init`` removes the leftovers of a crash).
PART = ".part"


def write_planes(
    path: Path,
    shape: tuple[int, int, int],
    dtype: np.dtype | str,
    planes: Iterable[np.ndarray],
    attributes: dict[str, Any] | Callable[[], dict[str, Any]],
    *,
    durable: bool = True,
) -> None:
    """Write (X, Y) planes, z in order, as the Zarr array ``path`` with ``attributes``
    (or what ``attributes()`` returns once every plane is written: a hash of them).

    Written into a hidden sibling folder and renamed into place when complete, flushed
    to disk first (unless not ``durable``: a temporary array, which a crash need not
    keep; flushing a 1 GB volume's chunks took 7-10 s on a busy disk): ``path`` is
    either absent or whole, even after a crash. A full disk raises ``DiskFull`` (507 in
    the server) and leaves nothing behind.
    """
    import zarr
    from zarr.codecs import BloscCodec

    dtype = np.dtype(dtype)
    _check_layout(path, shape, dtype)
    staging = path.with_name(f".{path.name}.{secrets.token_hex(4)}{PART}")
    try:
        array = zarr.create_array(
            staging,
            shape=shape[::-1],
            chunks=tuple(min(c, n) for c, n in zip(CHUNK, shape, strict=True))[::-1],
            dtype=dtype,
            compressors=BloscCodec(**BLOSC),
            fill_value=0,
            zarr_format=3,
            dimension_names=AXES,
        )
        _fill(array, shape, dtype, planes)
        array.attrs.update(_jsonable(attributes() if callable(attributes) else attributes))
        if durable:
            sync_tree(staging)
        os.replace(staging, path)
        if durable:
            fsync_dir(path.parent)
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        raise DiskFull(
            "disk full: the server's data folder ran out of space while storing the "
            "voxels, and nothing of them was kept; free space there, then try again."
        ) from None
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _fill(
    array: Any, shape: tuple[int, int, int], dtype: np.dtype, planes: Iterable[np.ndarray]
) -> None:
    """Buffer ``CHUNK[2]`` planes (one layer of chunks) at a time and write them."""
    depth = array.chunks[0]
    slab = np.zeros((depth, shape[1], shape[0]), dtype=dtype)
    z = 0
    for plane in planes:
        if z >= shape[2] or plane.shape != shape[:2]:
            raise ValueError(f"plane {z} of shape {plane.shape} does not fit a {shape} volume")
        slab[z % depth] = plane.T
        z += 1
        if z % depth == 0 or z == shape[2]:
            start = (z - 1) // depth * depth
            array[start:z] = slab[: z - start]
    if z != shape[2]:
        raise ValueError(f"got {z} planes for a volume of {shape[2]} slices")


def write_array(path: Path, data: np.ndarray, attributes: dict[str, Any]) -> None:
    """:func:`write_planes` of an (X, Y, Z) array (or memory map) held whole already."""
    planes = (data[:, :, k] for k in range(data.shape[2]))
    write_planes(path, data.shape, data.dtype, planes, attributes)


class Voxels:
    """A stored volume's (X, Y, Z) voxels, read lazily: numpy basic indexing (integers,
    slices with steps of 1 or more) reads and decompresses only the chunks the selection
    crosses and returns a numpy array; ``np.asarray`` reads everything. ``stored`` is
    the ``zarr.Array`` itself, (Z, Y, X). ``cache`` (a :class:`miss.surface.blocks.ChunkCache`,
    keyed by file): chunks kept between reads (a server's slices), else each read
    decompresses what it needs."""

    ndim = 3

    def __init__(
        self,
        stored: Any,
        folder: Path | None = None,
        fill: float = 0,
        cache: ChunkCache | None = None,
    ) -> None:
        self.stored, self.folder, self.fill, self.cache = stored, folder, fill, cache

    @property
    def shape(self) -> tuple[int, int, int]:
        """Voxels along (X, Y, Z)."""
        return tuple(self.stored.shape[::-1])

    @property
    def chunks(self) -> tuple[int, int, int]:
        """Voxels per chunk along (X, Y, Z)."""
        return tuple(self.stored.chunks[::-1])

    @property
    def dtype(self) -> np.dtype:
        """The stored voxels' type."""
        return np.dtype(self.stored.dtype)

    @property
    def size(self) -> int:
        """Voxels in all."""
        return math.prod(self.shape)

    @property
    def nbytes(self) -> int:
        """Bytes of all voxels once read (uncompressed)."""
        return self.size * self.dtype.itemsize

    def __getitem__(self, key: Any) -> np.ndarray:
        key = _xyz(key)
        picked = self._picked(key)
        if picked is None:  # an index this does not read itself (out of range, steps < 1)
            return np.asarray(self.stored[key[::-1]]).T
        box, steps, drop = picked
        out = self._read(box, steps)
        return out[tuple(0 if d else slice(None) for d in drop)]

    def _picked(
        self, key: tuple[Any, ...]
    ) -> tuple[list[tuple[int, int]], list[int], list[bool]] | None:
        """Per axis: the voxels to read (start, stop), the step, whether the axis goes
        (an integer index); None for what zarr should answer (its errors included)."""
        if self.folder is None:
            return None
        box, steps, drop = [], [], []
        for k, n in zip(key, self.shape, strict=True):
            if isinstance(k, int | np.integer) and not isinstance(k, bool):
                i = int(k) + n if k < 0 else int(k)
                if not 0 <= i < n:
                    return None
                box.append((i, i + 1))
                steps.append(1)
                drop.append(True)
            elif isinstance(k, slice):
                start, stop, step = k.indices(n)
                if step < 1:
                    return None
                stop = max(start, stop)
                box.append((start, stop))
                steps.append(step)
                drop.append(False)
            else:
                return None
        return box, steps, drop

    def _read(self, box: list[tuple[int, int]], steps: list[int]) -> np.ndarray:
        """Every ``steps``-th voxel of ``box`` ((start, stop) per axis) as an (X, Y, Z)
        F-ordered array, filled chunk by chunk (:meth:`chunk`) from the chunks holding one
        of those voxels, never more than the answer plus a chunk a thread: a strided
        read of a large volume (a preview) stays small. Decompression is spread over the
        cores when there are many chunks."""
        picks = [
            _lattice(a, b, st, c) for (a, b), st, c in zip(box, steps, self.chunks, strict=True)
        ]
        out = np.empty([len(range(a, b, st)) for (a, b), st in zip(box, steps, strict=True)],
                       dtype=self.dtype, order="F")  # fmt: skip
        if out.size == 0:
            return out
        jobs = list(itertools.product(*picks))

        def put(job: tuple[tuple[int, slice, slice], ...]) -> None:
            chunk = self.chunk((job[0][0], job[1][0], job[2][0]))
            out[tuple(j[2] for j in job)] = chunk[tuple(j[1] for j in job)]

        if len(jobs) < _PARALLEL_CHUNKS:
            for job in jobs:
                put(job)
        else:  # Blosc decompresses without the GIL
            with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
                list(pool.map(put, jobs))
        return out

    def min(self) -> Any:
        """The smallest voxel, read one layer of chunks at a time."""
        return min(layer.min() for layer in self.layers())

    def max(self) -> Any:
        """The largest voxel, read one layer of chunks at a time."""
        return max(layer.max() for layer in self.layers())

    def layers(self) -> Iterator[np.ndarray]:
        """The voxels as (X, Y, n) slabs, one layer of chunks (n slices) each, z in order."""
        depth = self.chunks[2]
        for start in range(0, self.shape[2], depth):
            yield self[:, :, start : start + depth]

    def chunk(self, index: tuple[int, int, int]) -> np.ndarray:
        """Chunk ``index`` (x, y, z chunk numbers) as an (X, Y, Z) array of the full chunk
        shape (Zarr stores the edge chunks whole), read straight from its file.

        What blockwise surfaces read: through ``zarr`` each chunk crosses to its event
        loop's thread and back, 1.05 ms a 64³ int16 chunk against 0.44 ms here (the file
        and Blosc's ``decompress``; measured on 512 x 512 x 600). The header's sizes are
        checked before a byte is decompressed, so a damaged file cannot ask for more
        memory than a chunk; a missing file is a chunk of the fill value, as in Zarr.
        """
        if self.folder is None:
            box = tuple(slice(i * c, (i + 1) * c) for i, c in zip(index, self.chunks, strict=True))
            return self[box]
        where = self.folder.joinpath("c", *(str(int(i)) for i in index[::-1]))
        if self.cache is not None:
            return self.cache.get((str(where),), lambda: self._from_file(where))
        return self._from_file(where)

    def _from_file(self, where: Path) -> np.ndarray:
        """The chunk stored in the file ``where`` (the fill value when there is none)."""
        shape = self.stored.chunks  # (Z, Y, X)
        size = math.prod(shape) * self.dtype.itemsize
        try:
            raw = where.read_bytes()
        except FileNotFoundError:
            return np.full(shape[::-1], self.fill, dtype=self.dtype, order="F")
        if (
            len(raw) < 16
            or int.from_bytes(raw[4:8], "little") != size
            or int.from_bytes(raw[12:16], "little") != len(raw)
        ):
            raise UnreadableVolume(
                f"{where}: not a Blosc chunk of {size} bytes; restore the data folder "
                "from a MISS backup."
            )
        from numcodecs import blosc

        flat = np.frombuffer(blosc.decompress(raw), dtype=self.dtype.newbyteorder("<"))
        return flat.reshape(shape).T

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        data = self[...]
        return data if dtype is None else data.astype(dtype)

    def __repr__(self) -> str:
        return f"Voxels(shape={self.shape}, dtype={self.dtype}, chunks={self.chunks})"


def _lattice(start: int, stop: int, step: int, size: int) -> list[tuple[int, slice, slice]]:
    """Along one axis, for the voxels ``range(start, stop, step)``: each chunk (of
    ``size``) holding one of them, with where they are in the chunk and in the answer."""
    found = []
    for c in range(start // size, (stop - 1) // size + 1) if stop > start else ():
        c0 = c * size
        first = max(0, -(-(c0 - start) // step))  # the first voxel at or past the chunk
        last = (min(stop, c0 + size) - 1 - start) // step
        if first <= last:
            at = start + first * step - c0
            found.append(
                (c, slice(at, at + (last - first) * step + 1, step), slice(first, last + 1))
            )
    return found


def _xyz(key: Any) -> tuple[Any, ...]:
    """A basic numpy index of an (X, Y, Z) array as three entries (Ellipsis filled in)."""
    key = key if isinstance(key, tuple) else (key,)
    if any(k is None or isinstance(k, np.ndarray | list) for k in key):
        raise IndexError("stored voxels take integers and slices only (no new axes, no arrays)")
    if Ellipsis in key:
        at = key.index(Ellipsis)
        key = key[:at] + (slice(None),) * (3 - len(key) + 1) + key[at + 1 :]
    return key + (slice(None),) * (3 - len(key))


def open_array(
    path: Path, cache: ChunkCache | None = None
) -> tuple[Voxels, np.ndarray, dict[str, Any]]:
    """The stored voxels (lazy, read-only :class:`Voxels`, reading through ``cache`` if
    given), their (4, 4) affine and the attributes, after checking ``zarr.json`` against
    what :func:`write_planes` writes."""
    import zarr

    meta = read_metadata(path)
    array = zarr.open_array(path, mode="r", zarr_format=3)
    fill = meta.get("fill_value", 0)
    fill = fill if isinstance(fill, int | float) and not isinstance(fill, bool) else 0
    voxels = Voxels(array, path, fill, cache)
    return voxels, _affine(path, meta["attributes"]), dict(meta["attributes"])


def read(path: Path, in_memory_max: int, cache: ChunkCache | None = None) -> np.ndarray | Voxels:
    """The voxels at ``path``: a read-only (X, Y, Z) Fortran-order numpy array when they
    take at most ``in_memory_max`` bytes (decompressed), else the lazy :class:`Voxels`
    (reading through ``cache``, if given)."""
    voxels, _, _ = open_array(path, cache)
    if voxels.nbytes > in_memory_max:
        return voxels
    data = voxels[...]  # (X, Y, Z) in Fortran order, assembled from the chunks
    data.flags.writeable = False
    return data


def same_voxels(path: Path, data: np.ndarray) -> bool:
    """True when the array at ``path`` holds exactly ``data``, compared slab by slab."""
    voxels, _, _ = open_array(path)
    if voxels.shape != data.shape or voxels.dtype != data.dtype:
        return False
    depth = voxels.chunks[2]
    return all(
        np.array_equal(layer, data[:, :, k * depth : (k + 1) * depth], equal_nan=True)
        for k, layer in enumerate(voxels.layers())
    )


def read_metadata(path: Path) -> dict[str, Any]:
    """``zarr.json`` of the array at ``path``, refused unless MISS could have written it."""
    where = path / "zarr.json"
    try:
        with open(where, "rb") as f:
            raw = f.read(_MAX_META_BYTES + 1)
        meta = json.loads(raw) if len(raw) <= _MAX_META_BYTES else None
    except FileNotFoundError:
        raise UnreadableVolume(f"{path}: no zarr.json; the stored volume is missing.") from None
    except ValueError:
        meta = None
    problem = _metadata_problem(meta)
    if problem:
        raise UnreadableVolume(
            f"{where}: {problem}; this is not a volume MISS stored: restore the data "
            "folder from a MISS backup."
        )
    assert isinstance(meta, dict)
    return meta


def _metadata_problem(meta: Any) -> str:
    """What makes ``meta`` other than MISS's own Zarr metadata ('' when nothing)."""
    if not isinstance(meta, dict) or meta.get("zarr_format") != 3:
        return "not Zarr v3 array metadata"
    shape = meta.get("shape")
    chunks = meta.get("chunk_grid", {}).get("configuration", {}).get("chunk_shape")
    if not _ints(shape, 1, 1 << 20) or not _ints(chunks, 1, _MAX_CHUNK_SIDE):
        return f"shape {shape} / chunks {chunks} are not three positive sizes"
    if meta.get("node_type") != "array" or meta.get("chunk_grid", {}).get("name") != "regular":
        return "not a regular array"
    if meta.get("data_type") not in DTYPES:
        return f"data type {meta.get('data_type')!r} is not one MISS stores"
    if meta.get("storage_transformers"):
        return "storage transformers MISS never writes"
    if meta.get("dimension_names") != list(AXES):
        return f"dimension names {meta.get('dimension_names')} are not {list(AXES)}"
    encoding = meta.get("chunk_key_encoding")
    if encoding != {"name": "default", "configuration": {"separator": "/"}}:
        return f"chunk key encoding {encoding} is not the default"
    codecs = meta.get("codecs")
    if not isinstance(codecs, list) or len(codecs) != 2:
        return "codecs other than bytes + blosc"
    one_byte = np.dtype(meta["data_type"]).itemsize == 1  # zarr says no endian for those
    if codecs[0] not in (_BYTES, *([{"name": "bytes"}] if one_byte else [])):
        return f"first codec {codecs[0]} is not little-endian bytes"
    blosc = codecs[1].get("configuration", {}) if isinstance(codecs[1], dict) else {}
    if codecs[1].get("name") != "blosc" or blosc.get("cname") != "zstd":
        return f"second codec {codecs[1]} is not blosc with zstd"
    if not isinstance(meta.get("attributes"), dict):
        return "no attributes"
    return ""


def _ints(value: Any, lo: int, hi: int) -> bool:
    return (
        isinstance(value, list)
        and len(value) == 3
        and all(isinstance(v, int) and lo <= v <= hi for v in value)
    )


def _affine(path: Path, attributes: dict[str, Any]) -> np.ndarray:
    try:
        affine = np.array(attributes["affine"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        affine = np.zeros(0)
    if affine.shape != (4, 4) or not np.isfinite(affine).all():
        raise UnreadableVolume(
            f"{path}: its 'affine' attribute is not a finite 4 x 4 matrix; restore the "
            "data folder from a MISS backup."
        )
    return affine


def nbytes(path: Path) -> int:
    """Bytes of the voxels of the array at ``path`` once decompressed (0 when absent)."""
    try:
        meta = read_metadata(path)
    except UnreadableVolume:
        return 0
    return math.prod(meta["shape"]) * np.dtype(meta["data_type"]).itemsize


def _check_layout(path: Path, shape: tuple[int, int, int], dtype: np.dtype) -> None:
    """Refuse, before writing, what :func:`open_array` would refuse after."""
    if len(shape) != 3 or min(shape) < 1:
        raise ValueError(f"{path.name}: shape {shape} is not an (X, Y, Z) volume")
    if dtype.name not in DTYPES or not dtype.isnative:
        raise ValueError(f"{path.name}: dtype {dtype} is not one MISS stores ({sorted(DTYPES)})")


def _jsonable(value: Any) -> Any:
    """numpy arrays and scalars in attributes to plain JSON values."""
    return json.loads(
        json.dumps(value, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o))
    )


def fsync_dir(path: Path) -> None:
    """Make a rename or a new entry in the folder ``path`` survive a crash of the machine."""
    fd = os.open(path, os.O_RDONLY | os.O_DIRECTORY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def sync_tree(folder: Path) -> None:
    """fsync every file under ``folder`` and the folders themselves."""
    for path in sorted(folder.rglob("*"), reverse=True):  # files before their folders
        if path.is_file():
            with open(path, "rb") as f:
                os.fsync(f.fileno())
        elif path.is_dir():
            fsync_dir(path)
    fsync_dir(folder)
