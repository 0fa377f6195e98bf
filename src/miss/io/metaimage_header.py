"""A small MetaImage header parser (``Key = Value`` lines, ``ElementDataFile`` last)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from miss.errors import UnreadableVolume

#: MetaIO element types -> numpy kind and size (MET_LONG is 4 bytes in MetaIO).
TYPES = {
    "MET_CHAR": "i1",
    "MET_UCHAR": "u1",
    "MET_SHORT": "i2",
    "MET_USHORT": "u2",
    "MET_INT": "i4",
    "MET_UINT": "u4",
    "MET_LONG": "i4",
    "MET_ULONG": "u4",
    "MET_LONG_LONG": "i8",
    "MET_ULONG_LONG": "u8",
    "MET_FLOAT": "f4",
    "MET_DOUBLE": "f8",
}


@dataclass(frozen=True)
class MetaHeader:
    """What the fallback reader needs; geometry is LPS, ``direction`` one axis per column."""

    sizes: list[int]
    dtype: np.dtype
    channels: int
    spacing: np.ndarray
    origin: np.ndarray
    direction: np.ndarray
    compressed: bool
    compressed_size: int | None  # CompressedDataSize as declared, if any
    header_size: int
    data_file: Path | None  # None: data follows the header (LOCAL)
    data_offset: int


def parse(path: Path, text: bytes) -> MetaHeader:
    """Parse the header at the start of ``text``; ``ElementDataFile`` ends it."""
    fields, offset = _fields(text)
    for required in ("NDims", "DimSize", "ElementType", "ElementDataFile"):
        if required not in fields:
            raise UnreadableVolume(f"{path.name}: bad MetaImage header: '{required}' is missing.")
    if fields["ElementType"] not in TYPES:
        raise UnreadableVolume(
            f"{path.name}: MetaImage ElementType {fields['ElementType']} is not supported."
        )
    try:
        return _header(path, fields, offset)
    except ValueError as exc:
        raise UnreadableVolume(f"{path.name}: bad MetaImage header ({exc}).") from exc


def _fields(text: bytes) -> tuple[dict[str, str], int]:
    fields: dict[str, str] = {}
    pos = 0
    while pos < len(text):
        end = text.find(b"\n", pos)
        end = len(text) if end < 0 else end
        line = text[pos:end].decode("latin-1").strip()
        pos = end + 1
        if "=" in line:
            key, value = (part.strip() for part in line.split("=", 1))
            fields[key] = value
            if key == "ElementDataFile":
                break
    return fields, pos


def _header(path: Path, fields: dict[str, str], offset: int) -> MetaHeader:
    ndims = int(fields["NDims"])
    sizes = [int(v) for v in fields["DimSize"].split()]
    msb = fields.get("BinaryDataByteOrderMSB", fields.get("ElementByteOrderMSB", "False"))
    dtype = np.dtype((">" if msb.lower() == "true" else "<") + TYPES[fields["ElementType"]])
    spacing = _numbers(fields, ("ElementSpacing", "ElementSize"), [1.0] * ndims)
    origin = _numbers(fields, ("Offset", "Origin", "Position"), [0.0] * ndims)
    matrix = _numbers(
        fields, ("TransformMatrix", "Rotation", "Orientation"), list(np.eye(ndims).ravel())
    )
    # MetaIO stores one axis direction after another: those are the columns.
    direction = np.array(matrix, float).reshape(ndims, ndims).T
    data = fields["ElementDataFile"]
    return MetaHeader(
        sizes=sizes,
        dtype=dtype,
        channels=int(fields.get("ElementNumberOfChannels", "1")),
        spacing=np.array(spacing[:3], float),
        origin=np.array(origin[:3], float),
        direction=direction[:3, :3],
        compressed=fields.get("CompressedData", "False").lower() == "true",
        compressed_size=int(fields["CompressedDataSize"])
        if "CompressedDataSize" in fields
        else None,
        header_size=int(fields.get("HeaderSize", "0")),
        data_file=None if data.upper() == "LOCAL" else path.parent / data,
        data_offset=offset,
    )


def _numbers(fields: dict[str, str], keys: tuple[str, ...], default: list[float]) -> list[float]:
    for key in keys:
        if key in fields:
            return [float(v) for v in fields[key].split()]
    return default
