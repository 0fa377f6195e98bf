"""MetaImage reader (``.mha``, ``.mhd`` + ``.raw``/``.zraw``).

MISS's own small parser (:mod:`miss.io.metaimage_header`) reads the header first and
checks it: a data file outside the header's folder and sizes the data cannot hold are
refused before anything is allocated. It then reads the voxels itself (raw or zlib, LOCAL
or one data file), inflating compressed data once (memory grows with what the data really
inflates to, never past the declared size) and refusing data that is damaged or falls
short; SimpleITK reads only the variants it lacks (ASCII data, lists of data files, 4-D
images, element types it does not know).

SimpleITK is kept away from the rest because hostile headers hang it (a TransformMatrix
holding 1e308), crash the process (NDims = 100000), or make it print on stderr; and
because it inflates only ``CompressedDataSize`` bytes and leaves the rest of the image
uninitialised, without an error (frogtissue.mhd declares 260020 of its 262087 bytes,
so its last four slices came back as random values).
"""

from __future__ import annotations

import math
import zlib
from pathlib import Path

import numpy as np

from miss.errors import UnreadableVolume, UnsupportedFormat
from miss.io import codecs, itk
from miss.io.common import affine_from, check_declared_size, make_volume, no_series, zyx_to_xyz
from miss.io.metaimage_header import (
    MetaHeader,
    data_file_outside,
    data_file_spec,
    fields_of,
    parse,
)
from miss.types import Volume

#: Every MetaImage header fits in this many bytes at the start of its file.
HEADER_BYTES = 1 << 20


def sniff(path: Path, head: bytes) -> bool:
    """``.mha``/``.mhd`` names, or a header starting with ``ObjectType`` or ``NDims``."""
    return path.suffix.lower() in (".mha", ".mhd") or head.lstrip().startswith(
        (b"ObjectType", b"NDims")
    )


def read(path: Path, series: str | None) -> Volume:
    """Read with MISS's own parser; SimpleITK only for the variants it lacks.

    The header is checked first either way: a data file outside the header's folder,
    sizes the data cannot hold and damaged compressed data are refused before anything
    (SimpleITK included) allocates or reads the voxels.
    """
    no_series(path, series, "MetaImage")
    text = _header_text(path)
    fields_of(path, text)  # refused here, naming the file, when MetaIO would read it otherwise
    outside = data_file_outside(text)
    if outside:
        raise UnreadableVolume(
            f"{path.name}: ElementDataFile {outside!r} is outside the header's folder "
            "(absolute or '..'); put the data file beside the header and name it without a folder."
        )
    try:
        header: MetaHeader | None = parse(path, text)
    except UnsupportedFormat:
        header = None  # an ElementType MISS's parser lacks (shape checked): SimpleITK may read it
    if header is not None and not header.unsupported:
        _check_data(path, header)
        mismatch = _compressed_size_mismatch(path, header)
        return read_fallback(path, notes=[mismatch] if mismatch else [])
    if header is not None:
        check_declared_size(path, [*header.sizes, header.channels], header.dtype.itemsize)
    try:
        image = itk.read_image(path, on_disk=itk.folder_bytes(path))
        return itk.to_volume(path, image, "metaimage")
    except UnsupportedFormat as exc:
        if header is not None:  # a variant MISS's reader lacks: it would read garbage
            raise UnreadableVolume(
                f"{exc}; MISS's own reader does not read {header.unsupported}: re-save the "
                "image as one binary .mha."
            ) from exc
        return read_fallback(path, notes=[f"{exc}; read with MISS's own MetaImage parser"])


def read_fallback(path: Path, notes: list[str] | None = None) -> Volume:
    """MISS's own reader: LOCAL or one detached data file, raw or zlib-compressed.

    (Named for its first role, the fallback after SimpleITK; it now reads most files.)
    """
    text = path.read_bytes()
    header = parse(path, text)
    need = _need(header)
    payload = _payload(path, header, text, need)
    if len(payload) < need and header.compressed:
        raise UnreadableVolume(
            f"{path.name}: the compressed voxel data is truncated: it inflates to {len(payload)} "
            f"of the {need} bytes DimSize calls for; copy the data file again."
        )
    if len(payload) < need:
        raise _truncated(path, len(payload), need)
    count = need // header.dtype.itemsize
    values = np.frombuffer(payload, dtype=header.dtype, count=count).astype(
        header.dtype.newbyteorder("=")
    )
    zyx = values.reshape(header.sizes[::-1] + [header.channels])[..., 0]
    notes = list(notes or [])
    if header.channels > 1:
        notes.append(f"{header.channels} channels per voxel: read the first")
    affine = affine_from(header.direction, header.spacing, header.origin)
    return make_volume(path, zyx_to_xyz(zyx), affine, "metaimage", notes=notes)


def _header_text(path: Path) -> bytes:
    """The start of the file: every MetaImage header fits in its first MiB."""
    with path.open("rb") as stream:
        return stream.read(HEADER_BYTES)


def _need(header: MetaHeader) -> int:
    """Voxel bytes the header declares."""
    return math.prod(header.sizes) * header.channels * header.dtype.itemsize


def _truncated(path: Path, got: int, need: int) -> UnreadableVolume:
    return UnreadableVolume(
        f"{path.name}: the voxel data is truncated: {got} of {need} bytes; copy the data file "
        "again or fix DimSize."
    )


def _missing(path: Path, header: MetaHeader) -> UnreadableVolume:
    name = header.data_file.name if header.data_file else "?"
    return UnreadableVolume(
        f"{path.name}: data file {name} is missing; the header names it in ElementDataFile. "
        "Put it beside the header."
    )


def _data_bytes(path: Path, header: MetaHeader) -> int | None:
    """Bytes of voxel data on disk (after HeaderSize), None when the data file is missing."""
    if header.data_file is None:
        available = path.stat().st_size - header.data_offset
    elif header.data_file.is_file():
        available = header.data_file.stat().st_size
    else:
        return None
    return available - max(header.header_size, 0)


def _check_data(path: Path, header: MetaHeader) -> None:
    """Refuse declared sizes the data cannot hold. Compressed data is inflated once, by
    :func:`read_fallback`, at most to the declared size, and refused there when it falls
    short (SimpleITK would fill the rest with whatever memory held, without an error)."""
    available = _data_bytes(path, header)
    shape = [*header.sizes, header.channels]
    if available is None:  # before SimpleITK, which prints its own complaint on stderr
        raise _missing(path, header)
    if not header.compressed:
        check_declared_size(path, shape, header.dtype.itemsize, fix="fix DimSize")
        if available < _need(header):
            raise _truncated(path, max(available, 0), _need(header))
        return
    check_declared_size(path, shape, header.dtype.itemsize, max(available, 0), fix="fix DimSize")
    codecs.check_declared(path, shape, header.dtype, max(available, 0), "zlib")


def _compressed_size_mismatch(path: Path, header: MetaHeader) -> str:
    """Why SimpleITK would silently misread this file, or "" when it will not."""
    if not header.compressed or header.compressed_size is None:
        return ""
    available = _data_bytes(path, header)
    if available is None or available == header.compressed_size:
        return ""
    return (
        f"the header's CompressedDataSize ({header.compressed_size}) disagrees with the "
        f"{available} compressed bytes present; all of them were inflated"
    )


def _payload(path: Path, header: MetaHeader, text: bytes, need: int) -> bytes:
    """The voxel bytes (at most ``need`` of them once inflated)."""
    if header.data_file is None:
        data = text[header.data_offset :]
    elif not header.data_file.is_file():
        raise _missing(path, header)
    else:
        data = header.data_file.read_bytes()
    if header.header_size > 0:
        data = data[header.header_size :]
    if not header.compressed:
        return data
    try:
        return codecs.inflate(data, "zlib", need, concatenated=False)
    except (zlib.error, ValueError) as exc:
        raise UnreadableVolume(
            f"{path.name}: the compressed voxel data is damaged ({exc}); copy it again."
        ) from exc


def data_file_named(path: Path) -> str:
    """The data file a MetaImage header names, as MetaIO reads it ("" for LOCAL data)."""
    text = _header_text(path)
    fields_of(path, text)
    spec = data_file_spec(text)
    return "" if spec.upper() == "LOCAL" else spec
