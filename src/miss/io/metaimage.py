"""MetaImage reader (``.mha``, ``.mhd`` + ``.raw``/``.zraw``).

SimpleITK reads it first (geometry already LPS). If SimpleITK fails, MISS's own small
parser (:mod:`miss.io.metaimage_header`) tries, which also produces the clear messages
for a missing or truncated data file.

MISS's parser also goes first when ``CompressedDataSize`` disagrees with the bytes on
disk: ITK inflates only the declared bytes and leaves the rest of the image buffer
uninitialised, without an error (frogtissue.mhd declares 260020 of its 262087 bytes,
so its last four slices come back as random values).
"""

from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from miss.errors import UnreadableVolume, UnsupportedFormat
from miss.io import itk
from miss.io.common import affine_from, make_volume, no_series, zyx_to_xyz
from miss.io.metaimage_header import MetaHeader, parse
from miss.types import Volume


def sniff(path: Path, head: bytes) -> bool:
    """``.mha``/``.mhd`` names, or a header starting with ``ObjectType`` or ``NDims``."""
    return path.suffix.lower() in (".mha", ".mhd") or head.lstrip().startswith(
        (b"ObjectType", b"NDims")
    )


def read(path: Path, series: str | None) -> Volume:
    """Read with SimpleITK; on failure, with MISS's own parser (and note why)."""
    no_series(path, series, "MetaImage")
    mismatch = _compressed_size_mismatch(path)
    if mismatch:
        return read_fallback(path, notes=[mismatch])
    try:
        return itk.to_volume(path, itk.read_image(path), "metaimage")
    except UnsupportedFormat as exc:
        return read_fallback(path, notes=[f"{exc}; read with MISS's own MetaImage parser"])


def read_fallback(path: Path, notes: list[str] | None = None) -> Volume:
    """MISS's own reader: LOCAL or one detached data file, raw or zlib-compressed."""
    text = path.read_bytes()
    header = parse(path, text)
    payload = _payload(path, header, text)
    count = int(np.prod(header.sizes, dtype=np.int64)) * header.channels
    need = count * header.dtype.itemsize
    if len(payload) < need:
        raise UnreadableVolume(
            f"{path.name}: the voxel data is truncated: {len(payload)} of {need} bytes; copy "
            "the data file again or fix DimSize."
        )
    values = np.frombuffer(payload, dtype=header.dtype, count=count).astype(
        header.dtype.newbyteorder("=")
    )
    zyx = values.reshape(header.sizes[::-1] + [header.channels])[..., 0]
    notes = list(notes or [])
    if header.channels > 1:
        notes.append(f"{header.channels} channels per voxel: read the first")
    affine = affine_from(header.direction, header.spacing, header.origin)
    return make_volume(path, zyx_to_xyz(zyx), affine, "metaimage", notes=notes)


def _compressed_size_mismatch(path: Path) -> str:
    """Why SimpleITK would silently misread this file, or "" when it will not."""
    text = path.read_bytes()
    try:
        header = parse(path, text)
    except UnreadableVolume:
        return ""  # let SimpleITK have a go; the fallback reports header problems
    if not header.compressed or header.compressed_size is None:
        return ""
    if header.data_file is None:
        available = len(text) - header.data_offset
    elif header.data_file.is_file():
        available = header.data_file.stat().st_size
    else:
        return ""
    available -= max(header.header_size, 0)
    if available == header.compressed_size:
        return ""
    return (
        f"the header's CompressedDataSize ({header.compressed_size}) disagrees with the "
        f"{available} compressed bytes present; read with MISS's own MetaImage parser, "
        "which inflates all of them"
    )


def _payload(path: Path, header: MetaHeader, text: bytes) -> bytes:
    if header.data_file is None:
        data = text[header.data_offset :]
    elif not header.data_file.is_file():
        raise UnreadableVolume(
            f"{path.name}: data file {header.data_file.name} is missing; the header names it "
            "in ElementDataFile. Put it beside the header."
        )
    else:
        data = header.data_file.read_bytes()
    if header.header_size > 0:
        data = data[header.header_size :]
    if not header.compressed:
        return data
    try:
        return zlib.decompressobj(zlib.MAX_WBITS | 32).decompress(data)
    except zlib.error as exc:
        raise UnreadableVolume(
            f"{path.name}: the compressed voxel data is damaged ({exc}); copy it again."
        ) from exc
