"""A small MetaImage header parser (``Key = Value`` lines, ``ElementDataFile`` last)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path, PurePath

import numpy as np

from miss.errors import UnreadableVolume, UnsupportedFormat

#: Most axes a header may declare (MetaIO itself stops at 10).
MAX_DIMS = 10
#: Largest magnitude accepted for spacing, origin and direction values (mm; 1000 km).
MAX_COORDINATE = 1e9
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

#: The other MetaIO element types (vectors, strings): left to SimpleITK.
OTHER_TYPES = {f"MET_{name}_ARRAY" for name in (t[4:] for t in TYPES)} | {
    "MET_STRING",
    "MET_ASCII_CHAR",
    "MET_FLOAT_MATRIX",
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
    unsupported: str = ""  # what MISS's reader lacks for this file ("" when it reads it)


def parse(path: Path, text: bytes) -> MetaHeader:
    """Parse the header at the start of ``text``; ``ElementDataFile`` ends it."""
    fields, offset = fields_of(path, text)
    for required in ("NDims", "DimSize", "ElementType", "ElementDataFile"):
        if required not in fields:
            raise UnreadableVolume(
                f"{path.name}: bad MetaImage header: '{required}' is missing; add it or "
                "re-save the image (ElementDataFile must be the last line)."
            )
    try:
        ndims, sizes, channels = _shape(fields)
        spacing, origin, direction = _geometry(fields, ndims)
        compressed_size = fields.get("CompressedDataSize")
        extra = (
            int(compressed_size) if compressed_size else None,
            int(fields.get("HeaderSize", "0")),
        )
    except ValueError as exc:
        raise UnreadableVolume(
            f"{path.name}: bad MetaImage header ({exc}); fix that field or re-save the image."
        ) from exc
    if fields["ElementType"] not in TYPES.keys() | OTHER_TYPES:
        raise UnreadableVolume(
            f"{path.name}: bad MetaImage header: ElementType {fields['ElementType']!r} is not "
            f"a MetaImage type; fix it (e.g. MET_SHORT) or re-save the image."
        )
    if fields["ElementType"] not in TYPES:  # checked last: SimpleITK may read it next
        raise UnsupportedFormat(
            f"{path.name}: MetaImage ElementType {fields['ElementType']} is not supported; "
            f"re-save with one of {', '.join(TYPES)}."
        )
    msb = fields.get("BinaryDataByteOrderMSB", fields.get("ElementByteOrderMSB", "False"))
    data = fields["ElementDataFile"]
    return MetaHeader(
        sizes=sizes,
        dtype=np.dtype((">" if msb.lower() == "true" else "<") + TYPES[fields["ElementType"]]),
        channels=channels,
        spacing=spacing[:3],
        origin=origin[:3],
        direction=direction[:3, :3],
        compressed=fields.get("CompressedData", "False").lower() == "true",
        compressed_size=extra[0],
        header_size=extra[1],
        data_file=None if data.upper() == "LOCAL" else path.parent / data,
        data_offset=offset,
        unsupported=_unsupported(fields, ndims, extra[1]),
    )


def _unsupported(fields: dict[str, str], ndims: int, header_size: int) -> str:
    """The MetaImage variants MISS's reader leaves to SimpleITK ("" for none)."""
    words = fields["ElementDataFile"].split()
    if words[:1] == ["LIST"] or (len(words) >= 4 and "%" in words[0]):
        return "several data files"
    if fields.get("BinaryData", "True").lower() == "false":
        return "ASCII voxel data"
    if ndims > 3:
        return f"a {ndims}-D image"
    return "HeaderSize -1" if header_size < 0 else ""


def fields_of(path: Path, text: bytes) -> tuple[dict[str, str], int]:
    """``_fields``, its refusals naming the file."""
    try:
        return _fields(text)
    except UnreadableVolume as exc:
        raise UnreadableVolume(f"{path.name}: {exc}") from None


def data_file_outside(text: bytes) -> str:
    """The ``ElementDataFile`` name that points outside the header's folder, else "".

    Checked on the field as MetaIO reads it, before SimpleITK follows it: a header must
    not make MISS read an arbitrary file (on a server, another user's data). Symbolic
    links inside the folder are not resolved, so a folder of links still works. The
    names after ``LIST`` and the pattern of ``NAME%03d.raw 1 10 1`` are checked too.
    """
    fields, offset = _fields(text)
    value = fields.get("ElementDataFile", "LOCAL")
    names = [value, *value.split()[:1]]
    if value.split()[:1] == ["LIST"]:
        names = text[offset:].decode("latin-1").split()
    return next((n for n in names if n.upper() != "LOCAL" and _outside(n)), "")


def data_file_spec(text: bytes) -> str:
    """The ``ElementDataFile`` value as MetaIO reads it ("LOCAL" when the data follows)."""
    return _fields(text)[0].get("ElementDataFile", "LOCAL")


def _outside(name: str) -> bool:
    parts = name.replace("\\", "/").split("/")
    return (
        name.startswith(("/", "\\"))
        or PurePath(name).is_absolute()
        or ".." in parts
        or (len(name) > 1 and name[1] == ":")
    )


#: What C's isspace() skips before a field name (Python's str.strip() skips more).
_C_SPACE = " \t\n\v\f\r"
#: The field that names the voxels' file and ends the header.
DATA_FIELD = "ElementDataFile"
#: A line that any spelling of MetaIO would take for the data-file field.
_DATA_FIELD_LINE = re.compile(rb"(?im)^[ \t\f\v]*element[ \t]*data[ \t]*file[ \t]*[=:]")


def _fields(text: bytes) -> tuple[dict[str, str], int]:
    """Header fields read the way MetaIO reads them, and where the header ends.

    MetaIO (``MET_Read``) takes a field name up to the first ``=`` **or** ``:`` on a line,
    trailing blanks cut, and matches it case-sensitively; the value follows any run of
    ``=``, ``:`` and blanks. MISS once split on ``=`` only, so ``ElementDataFile: /path``
    before a decoy ``ElementDataFile = LOCAL`` passed its check and was followed by
    SimpleITK. Any second line that some spelling could take for the data-file field is
    refused, and so is a known field without a separator (MetaIO would read its value
    from the next line).
    """
    fields: dict[str, str] = {}
    pos = 0
    while pos < len(text):
        end = text.find(b"\n", pos)
        end = len(text) if end < 0 else end
        raw = text[pos:end]
        pos = end + 1
        if b"\0" in raw:  # binary data: the header ended without its data-file field
            if _DATA_FIELD_LINE.match(raw.replace(b"\0", b"")):
                raise UnreadableVolume(
                    "bad MetaImage header: its data-file line holds a NUL byte; re-save the image."
                )
            break
        line = raw.decode("latin-1").lstrip(_C_SPACE)
        cut = min((i for i in (line.find("="), line.find(":")) if i >= 0), default=-1)
        name = (line[:cut] if cut >= 0 else line.split("\r")[0]).rstrip(" \t")
        if cut < 0:
            if name.rstrip() in _KNOWN:
                raise UnreadableVolume(
                    f"bad MetaImage header: the line {name!r} has no '=' and no value; write "
                    f"'{name} = value' on one line."
                )
            continue
        fields[name] = line[cut:].lstrip("=: \t").rstrip()
        if name == DATA_FIELD:
            _check_data_field(fields[name], text, pos)
            break
        if _DATA_FIELD_LINE.match(raw):
            raise _two_data_fields(name)
    return fields, pos


def _check_data_field(value: str, text: bytes, pos: int) -> None:
    if not value:
        raise UnreadableVolume(
            f"bad MetaImage header: '{DATA_FIELD}' has no value; write "
            f"'{DATA_FIELD} = LOCAL' or the data file's name on the same line."
        )
    _refuse_second_data_field(text, pos)


def _refuse_second_data_field(text: bytes, pos: int) -> None:
    """After ``ElementDataFile`` come voxels (LOCAL) or nothing: no second data field."""
    rest = text[pos : pos + (1 << 16)]
    found = _DATA_FIELD_LINE.search(rest)
    if found:
        raise _two_data_fields(found.group(0).decode("latin-1").strip(" =:"))


def _two_data_fields(name: str) -> UnreadableVolume:
    return UnreadableVolume(
        f"bad MetaImage header: it names its data file twice ({name!r} and "
        f"{DATA_FIELD!r}); keep one '{DATA_FIELD} = ...' line, the last of the header."
    )


#: Field names MetaIO reads for an image (``MetaObject`` and ``MetaImage``).
_KNOWN = frozenset(
    (
        "Comment",
        "ObjectType",
        "ObjectSubType",
        "TransformType",
        "NDims",
        "Name",
        "ID",
        "ParentID",
        "Color",
        "Position",
        "Origin",
        "Offset",
        "TransformMatrix",
        "Rotation",
        "Orientation",
        "CenterOfRotation",
        "AnatomicalOrientation",
        "DistanceUnits",
        "ElementSpacing",
        "ElementSize",
        "DimSize",
        "HeaderSize",
        "Modality",
        "SequenceID",
        "ElementMin",
        "ElementMax",
        "ElementNumberOfChannels",
        "ElementType",
        "CompressedData",
        "CompressedDataSize",
        "BinaryData",
        "BinaryDataByteOrderMSB",
        "ElementByteOrderMSB",
        "ElementDataFile",
    )
)


def _shape(fields: dict[str, str]) -> tuple[int, list[int], int]:
    """NDims, DimSize and channels, checked before anything is sized by them.

    SimpleITK crashes the process (segmentation fault) on some impossible headers such
    as ``NDims = 100000``, so these are refused here, before it sees the file.
    """
    ndims = int(fields["NDims"])
    sizes = [int(v) for v in fields["DimSize"].split()]
    channels = int(fields.get("ElementNumberOfChannels", "1"))
    if not 1 <= ndims <= MAX_DIMS:
        raise ValueError(f"NDims {ndims} is not 1 to {MAX_DIMS}")
    if len(sizes) != ndims or min(sizes) < 1 or channels < 1:
        raise ValueError(
            f"DimSize {fields['DimSize']!r} must give {ndims} positive sizes and "
            f"ElementNumberOfChannels ({channels}) must be at least 1"
        )
    if ndims < 3:
        raise ValueError(f"a {ndims}-D image; MISS needs a 3-D volume (NDims = 3)")
    return ndims, sizes, channels


def _geometry(fields: dict[str, str], ndims: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ElementSpacing, Offset and the direction matrix (one axis per column), checked.

    SimpleITK hangs on a TransformMatrix holding 1e308, so values must be finite and
    moderate, and the axes must span space, before it sees the file.
    """
    spacing_given = _numbers(fields, ("ElementSpacing", "ElementSize"), [1.0] * ndims)
    origin_given = _numbers(fields, ("Offset", "Origin", "Position"), [0.0] * ndims)
    matrix = _numbers(
        fields, ("TransformMatrix", "Rotation", "Orientation"), list(np.eye(ndims).ravel())
    )
    if len(matrix) != ndims * ndims:
        raise ValueError(f"TransformMatrix has {len(matrix)} values, not NDims^2 = {ndims**2}")
    spacing = np.array((spacing_given + [1.0] * ndims)[:ndims], float)  # short: MetaIO's defaults
    origin = np.array((origin_given + [0.0] * ndims)[:ndims], float)
    # MetaIO stores one axis direction after another: those are the columns.
    direction = np.array(matrix, float).reshape(ndims, ndims).T
    values = np.concatenate([spacing, origin, direction.ravel()])
    if not np.isfinite(values).all() or np.abs(values).max() > MAX_COORDINATE:
        raise ValueError(
            f"ElementSpacing, Offset and TransformMatrix must be finite numbers below "
            f"{MAX_COORDINATE:g}"
        )
    lengths = np.linalg.norm(direction, axis=0)
    if lengths.min() == 0 or abs(np.linalg.det(direction)) < 1e-6 * lengths.prod():
        raise ValueError("TransformMatrix is degenerate (an axis is zero or two are parallel)")
    return spacing, origin, direction


def _numbers(fields: dict[str, str], keys: tuple[str, ...], default: list[float]) -> list[float]:
    for key in keys:
        if key in fields:
            return [float(v) for v in fields[key].split()]
    return default
