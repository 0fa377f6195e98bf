"""A small NRRD header parser (NRRD0001-0005), detached ``data file:`` forms included.

pynrrd cannot read ``data file: NAME.%d 1 113 1`` (one file per slice), which is how
the classic raw-slice scans ship, so MISS parses the header itself. Only what a volume
needs is interpreted; unknown fields are kept as text.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from miss.errors import UnreadableVolume

#: NRRD type names (all spellings the spec allows) -> numpy kind and size.
TYPES = {
    **dict.fromkeys(["signed char", "int8", "int8_t"], "i1"),
    **dict.fromkeys(["uchar", "unsigned char", "uint8", "uint8_t"], "u1"),
    **dict.fromkeys(
        ["short", "short int", "signed short", "signed short int", "int16", "int16_t"], "i2"
    ),
    **dict.fromkeys(["ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"], "u2"),
    **dict.fromkeys(["int", "signed int", "int32", "int32_t"], "i4"),
    **dict.fromkeys(["uint", "unsigned int", "uint32", "uint32_t"], "u4"),
    **dict.fromkeys(
        [
            "longlong",
            "long long",
            "long long int",
            "signed long long",
            "signed long long int",
            "int64",
            "int64_t",
        ],
        "i8",
    ),
    **dict.fromkeys(
        ["ulonglong", "unsigned long long", "unsigned long long int", "uint64", "uint64_t"], "u8"
    ),
    "float": "f4",
    "double": "f8",
}
#: Most detached data files a header may list (one per slice of a very long scan).
MAX_DATA_FILES = 100_000
#: Bytes of a file searched for its header (a detached header is far smaller).
HEADER_LIMIT = 1 << 20
#: A line that any spelling would take for the ``data file`` field (not a ``key:=value``).
_DATA_FILE_LINE = re.compile(rb"(?im)^[ \t]*data[ \t]*file[ \t]*:(?!=)")
ENCODINGS = {"raw": "raw", "gzip": "gzip", "gz": "gzip", "bzip2": "bzip2", "bz2": "bzip2"}
ENCODINGS |= dict.fromkeys(["ascii", "text", "txt"], "ascii")


@dataclass(frozen=True)
class DataFiles:
    """Where the voxels are: attached (``files`` empty) or in one or more detached files.

    ``listing`` describes the files for messages, e.g. ``"CThead.1..113"``.
    """

    files: list[Path] = field(default_factory=list)
    listing: str = ""


@dataclass(frozen=True)
class NrrdHeader:
    """The parsed header: ``fields`` maps lower-case field names to their raw text."""

    fields: dict[str, str]
    data: DataFiles
    data_offset: int | None  # where attached data starts in the header file

    def get(self, name: str, default: str | None = None) -> str | None:
        """The raw text of field ``name``, else ``default``."""
        return self.fields.get(name, default)

    @property
    def sizes(self) -> list[int]:
        """Voxels along each axis (``sizes``)."""
        return [int(v) for v in self.fields["sizes"].split()]

    @property
    def dtype(self) -> np.dtype:
        """The stored value type in the file's byte order (``type``, ``endian``)."""
        endian = ">" if self.fields.get("endian", "little") == "big" else "<"
        return np.dtype(endian + TYPES[self.fields["type"]])

    @property
    def encoding(self) -> str:
        """The data's encoding, by its canonical name (``encoding``, default raw)."""
        return ENCODINGS[self.fields.get("encoding", "raw")]


def parse(path: Path, text: bytes) -> NrrdHeader:
    """Parse the header at the start of ``text`` (the bytes of the ``.nrrd``/``.nhdr`` file).

    Raises
    ------
    UnreadableVolume
        Wrong magic, missing required fields, unknown type or encoding.
    """
    if not re.match(rb"NRRD000[1-5]\r?\n", text[:9]):
        raise UnreadableVolume(
            f"{path.name}: not a NRRD file: it should start with 'NRRD0004' but starts with "
            f"{text[:8]!r}; check it was not renamed or damaged."
        )
    fields, listed, offset = _fields(text)
    header_end = len(text) if offset is None else offset
    if len(_DATA_FILE_LINE.findall(text[:header_end])) > 1:
        raise UnreadableVolume(
            f"{path.name}: bad NRRD header: it names its data file twice; keep one "
            "'data file:' line."
        )
    _validate(path, fields)
    try:
        data = _data_files(path, fields.get("data file"), listed)
    except (ValueError, TypeError, IndexError) as exc:
        raise UnreadableVolume(
            f"{path.name}: bad NRRD header: cannot use 'data file: {fields['data file']}' "
            f"({exc}); fix that line."
        ) from exc
    outside = [f.name for f in data.files if not _beside(path, f)]
    if outside:
        raise UnreadableVolume(
            f"{path.name}: the data file {outside[0]!r} is outside the header's folder "
            "(absolute or '..'); put the data beside the header and name it without a folder."
        )
    return NrrdHeader(fields, data, offset)


def data_file_spec(text: bytes) -> str:
    """The ``data file`` field of the header in ``text`` ("" when the data is attached)."""
    if not re.match(rb"NRRD000[1-5]\r?\n", text[:9]):
        return ""
    return _fields(text)[0].get("data file", "")


def _beside(header: Path, data: Path) -> bool:
    """True when ``data`` names a file in the header's folder or below it, by name alone.

    Symbolic links are not resolved: a folder of links to the real slices is fine, but a
    header must not point MISS at an arbitrary file (on a server, another user's data).
    """
    try:
        relative = data.relative_to(header.parent)
    except ValueError:
        return False
    return ".." not in relative.parts


def _validate(path: Path, fields: dict[str, str]) -> None:
    """Required fields present, type and encoding known, sizes matching dimension."""
    bad = f"{path.name}: bad NRRD header:"
    for required in ("type", "dimension", "sizes"):
        if required not in fields:
            raise UnreadableVolume(
                f"{bad} the required field '{required}' is missing; add it or re-save the NRRD."
            )
    if fields["type"] not in TYPES:
        raise UnreadableVolume(
            f"{bad} type '{fields['type']}' is not supported; use an integer or float type."
        )
    if fields.get("encoding", "raw") not in ENCODINGS:
        raise UnreadableVolume(
            f"{bad} encoding '{fields['encoding']}' is not supported; re-save as raw or gzip."
        )
    try:
        sizes = [int(v) for v in fields["sizes"].split()]
        dimension = int(fields["dimension"])
    except ValueError as exc:
        raise UnreadableVolume(
            f"{bad} 'sizes' and 'dimension' must be integers ({exc}); fix those lines."
        ) from exc
    if len(sizes) != dimension or min(sizes, default=0) < 1:
        raise UnreadableVolume(
            f"{bad} 'sizes: {fields['sizes']}' does not give {dimension} positive sizes; fix "
            "'sizes' (fastest axis first) or 'dimension'."
        )


def _fields(text: bytes) -> tuple[dict[str, str], list[str], int | None]:
    """Header fields, the file names after ``data file: LIST``, and where data starts."""
    fields: dict[str, str] = {}
    listed: list[str] = []
    pos = text.index(b"\n") + 1
    while pos < len(text):
        end = text.find(b"\n", pos)
        line = text[pos : len(text) if end < 0 else end].rstrip(b"\r").decode("latin-1")
        pos = len(text) if end < 0 else end + 1
        if not line:
            return fields, listed, pos if "data file" not in fields else None
        if fields.get("data file", "").split()[:1] == ["LIST"]:
            listed.append(line.strip())
        elif _is_field(line):
            key, value = line.split(": ", 1)
            fields[key.strip().lower().replace("datafile", "data file")] = value.strip()
    return fields, listed, None


def _is_field(line: str) -> bool:
    """``key: value`` is a field; ``# ...`` a comment; ``key:=value`` a free key/value pair."""
    if line.startswith("#") or ": " not in line:
        return False
    return ":=" not in line or line.index(": ") < line.index(":=")


def _data_files(header: Path, spec: str | None, listed: list[str]) -> DataFiles:
    """Resolve ``data file:``: one name, ``LIST`` (names follow), or ``FMT MIN MAX STEP``."""
    if spec is None:
        return DataFiles()
    parts = spec.split()
    folder = header.parent
    if parts[0] == "LIST":
        return DataFiles(
            [folder / n for n in listed], f"{len(listed)} files ({listed[0]} ...)" if listed else ""
        )
    if len(parts) >= 4 and "%" in parts[0]:
        first, last, step = (int(v) for v in parts[1:4])
        numbers = range(first, last + (1 if step > 0 else -1), step)
        if not 0 < len(numbers) <= MAX_DATA_FILES:
            raise ValueError(f"it numbers {len(numbers)} files, not 1 to {MAX_DATA_FILES}")
        names = [parts[0] % n for n in numbers]
        return DataFiles([folder / n for n in names], f"{names[0]}..{last}")
    return DataFiles([folder / spec], spec)
