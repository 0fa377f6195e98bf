"""NRRD reader (``.nrrd`` attached, ``.nhdr`` detached) on top of :mod:`nrrd_header`.

Voxels may sit after the header, in one detached file, or spread over many (``LIST``
or ``NAME.%d 1 113 1``), raw or compressed, in either byte order. Geometry comes from
``space directions``/``space origin`` converted to LPS; headers that give only
``spacings`` get axis-aligned steps, and a note says what was assumed.
"""

from __future__ import annotations

import math
import re
import zlib
from pathlib import Path

import numpy as np

from miss.errors import UnreadableVolume
from miss.io import codecs, nrrd_header
from miss.io.common import check_declared_size, make_volume, no_series
from miss.io.nrrd_header import NrrdHeader
from miss.types import Volume

#: Anatomical spaces -> sign flips that take their axes to LPS.
SPACES = {
    "right-anterior-superior": (-1, -1, 1),
    "left-anterior-superior": (1, -1, 1),
    "left-posterior-superior": (1, 1, 1),
}
SPACES |= {"".join(w[0] for w in name.split("-")): flips for name, flips in SPACES.items()}
#: Spaces with no anatomical meaning: taken as LPS, with a note.
GENERIC_SPACES = {"scanner-xyz", "3d-right-handed", "3d-left-handed"}
#: ``kinds`` values that mark an axis as spatial.
SPATIAL_KINDS = {"domain", "space"}


def sniff(path: Path, head: bytes) -> bool:
    """``.nrrd``/``.nhdr`` names or the ``NRRD000x`` magic."""
    return path.suffix.lower() in (".nrrd", ".nhdr") or head.startswith(b"NRRD000")


def read(path: Path, series: str | None) -> Volume:
    """Read a NRRD volume; non-spatial axes (vector components, time) keep index 0."""
    no_series(path, series, "NRRD")
    text = path.read_bytes()
    header = nrrd_header.parse(path, text)
    _check_sizes(path, header, text)
    values = _values(path, header, _payload(path, header, text))
    # NRRD lists the fastest axis first: a C-ordered reshape of the reversed sizes,
    # transposed back, is the Fortran-ordered (axis0, axis1, ...) view without a copy.
    array = values.reshape(header.sizes[::-1]).transpose()
    notes: list[str] = []
    spatial = _spatial_axes(path, header, notes)
    array = array[tuple(slice(None) if a in spatial else 0 for a in range(array.ndim))]
    return make_volume(
        path,
        array,
        _affine(path, header, spatial, notes),
        "nrrd",
        notes=notes,
        series_description=header.get("content", "") or "",
    )


def _check_sizes(path: Path, header: NrrdHeader, text: bytes) -> None:
    """Refuse absurd sizes before reading, inflating or allocating anything: compressed
    data is held to the caps of :mod:`miss.io.codecs` (byte skips count: they are
    inflated too)."""
    compressed = None
    if header.encoding in ("gzip", "bzip2"):
        if header.data.files:
            compressed = sum(f.stat().st_size for f in header.data.files if f.is_file())
        else:
            compressed = len(text) - (header.data_offset or len(text))
    check_declared_size(
        path,
        header.sizes,
        header.dtype.itemsize,
        compressed if header.encoding == "gzip" else None,
        fix="fix 'sizes' (fastest axis first)",
    )
    if compressed is not None:
        skipped = max(_skips(path, header)[1], 0) * max(len(header.data.files), 1)
        what = codecs.declared_text(header.sizes, header.dtype)
        decoded = _expected_bytes(header) + skipped
        codecs.check_decoded(path, decoded, compressed, header.encoding, what)


def _payload(path: Path, header: NrrdHeader, text: bytes) -> bytes:
    """Decoded voxel bytes (or ASCII text) from the attached data or the detached files."""
    if not header.data.files:
        if header.data_offset is None:
            raise UnreadableVolume(
                f"{path.name}: the header names no 'data file' and has no blank line before "
                "attached data; add 'data file: NAME' or re-save the NRRD."
            )
        return _decode(path, path.name, text[header.data_offset :], header)
    _check_present(path, header)
    share = _expected_bytes(header) // len(header.data.files)
    chunks = []
    for file in header.data.files:
        chunk = _decode(path, file.name, file.read_bytes(), header)
        if header.encoding != "ascii" and len(chunk) < share:
            raise _truncated(path, file.name, len(chunk), share)
        chunks.append(chunk)
    return b"".join(chunks)


def _check_present(path: Path, header: NrrdHeader) -> None:
    missing = [f for f in header.data.files if not f.is_file()]
    if not missing:
        return
    more = f" ({len(missing)} of {len(header.data.files)} are missing)" if len(missing) > 1 else ""
    raise UnreadableVolume(
        f"{path.name}: data file {missing[0].name} is missing{more}; the header lists "
        f"{header.data.listing} beside it. Copy the missing file(s) next to the header, or "
        "fix its 'data file:' line."
    )


def _decode(path: Path, name: str, chunk: bytes, header: NrrdHeader) -> bytes:
    """Skip lines, decompress, skip bytes: the order the NRRD spec applies them in.

    Compressed data is inflated only as far as the header's sizes need, so trailing
    data (or a bomb) never inflates in full.
    """
    lines, skip = _skips(path, header)
    start = 0
    for _ in range(lines):
        start = chunk.find(b"\n", start) + 1
        if start == 0:
            raise UnreadableVolume(
                f"{path.name}: 'line skip: {lines}' skips more lines than {name} has; fix "
                "'line skip' or copy the data again."
            )
    chunk = chunk[start:]
    share = _expected_bytes(header) // max(len(header.data.files), 1)
    if header.encoding in ("gzip", "bzip2"):
        if skip == -1:
            raise UnreadableVolume(
                f"{path.name}: 'byte skip: -1' (data at the end of the file) is only allowed "
                "with raw encoding; fix 'byte skip' or 'encoding'."
            )
        chunk = _inflate(path, name, chunk, header.encoding, skip + share)
    if skip == -1:  # "the data is at the end of the file"
        return chunk[len(chunk) - share :] if len(chunk) >= share else chunk
    return chunk[skip:]


def _skips(path: Path, header: NrrdHeader) -> tuple[int, int]:
    """``line skip`` and ``byte skip`` as integers (line skip >= 0, byte skip >= -1)."""
    try:
        lines, skip = (
            int(header.fields.get("line skip", "0")),
            int(header.fields.get("byte skip", "0")),
        )
    except ValueError as exc:
        raise UnreadableVolume(
            f"{path.name}: bad NRRD header: 'line skip' and 'byte skip' must be integers "
            f"({exc}); fix those lines."
        ) from exc
    if lines < 0 or skip < -1:
        raise UnreadableVolume(
            f"{path.name}: bad NRRD header: 'line skip: {lines}' / 'byte skip: {skip}' are out "
            "of range (line skip >= 0, byte skip >= -1); fix those lines."
        )
    return lines, skip


def _inflate(path: Path, name: str, chunk: bytes, encoding: str, limit: int) -> bytes:
    """At most ``limit`` bytes of gzip/zlib or bzip2 data (concatenated streams included)."""
    try:
        return codecs.inflate(chunk, encoding, limit)
    except (EOFError, OSError, zlib.error, ValueError) as exc:
        raise UnreadableVolume(
            f"{path.name}: the {encoding} data in {name} is truncated or damaged ({exc}); "
            "copy it again."
        ) from exc


def _values(path: Path, header: NrrdHeader, payload: bytes) -> np.ndarray:
    """Flat voxel values in file order, native byte order, writable."""
    count = math.prod(header.sizes)
    if header.encoding == "ascii":
        words = payload.split()
        if len(words) < count:
            raise _truncated(path, path.name, len(words), count, unit="values")
        try:
            return np.array(words[:count], dtype=header.dtype.newbyteorder("="))
        except (ValueError, OverflowError) as exc:
            raise UnreadableVolume(
                f"{path.name}: the ASCII voxel data holds something that is not a "
                f"{header.get('type')} number ({exc}); fix the data or the 'type' line."
            ) from exc
    if len(payload) < count * header.dtype.itemsize:
        raise _truncated(path, path.name, len(payload), count * header.dtype.itemsize)
    values = np.frombuffer(payload, dtype=header.dtype, count=count)
    return values.astype(header.dtype.newbyteorder("="))  # a writable, native-endian copy


def _expected_bytes(header: NrrdHeader) -> int:
    return math.prod(header.sizes) * header.dtype.itemsize


def _truncated(path: Path, name: str, got: int, need: int, unit: str = "bytes") -> UnreadableVolume:
    return UnreadableVolume(
        f"{path.name}: the voxel data is truncated: {name} holds {got} of the {need} {unit} "
        "the header's sizes and type call for; copy the data again or fix 'sizes'."
    )


def _spatial_axes(path: Path, header: NrrdHeader, notes: list[str]) -> list[int]:
    """Indices of the 3 spatial axes; other axes are read at index 0 (noted)."""
    sizes = header.sizes
    directions = header.get("space directions")
    kinds = (header.get("kinds") or "").split()
    if directions:
        vectors = _vectors(path, "space directions", directions)
        if len(vectors) != len(sizes):
            raise UnreadableVolume(
                f"{path.name}: bad NRRD header: 'space directions' gives {len(vectors)} entries "
                f"for {len(sizes)} axes; give one vector (or none) per axis."
            )
        spatial = [a for a, v in enumerate(vectors) if v is not None]
    elif len(sizes) == 3:
        spatial = [0, 1, 2]
    elif len(kinds) == len(sizes):
        spatial = [a for a, kind in enumerate(kinds) if kind.lower() in SPATIAL_KINDS]
    else:
        spatial = [a for a, n in enumerate(sizes) if n > 1]
    if len(spatial) != 3:
        raise UnreadableVolume(
            f"{path.name}: the NRRD has {len(spatial)} spatial axes (sizes {sizes}); MISS "
            "needs a 3-D volume: export the scan as one 3-D volume."
        )
    if len(sizes) > 3:
        notes.append(
            f"NRRD has {len(sizes)} axes (sizes {sizes}): read index 0 of the non-spatial ones"
        )
    return spatial


def _affine(path: Path, header: NrrdHeader, spatial: list[int], notes: list[str]) -> np.ndarray:
    """Voxel (i, j, k) to LPS mm from the space fields, or from ``spacings`` when absent."""
    flips = _space_flips(header.get("space"), notes)
    directions = header.get("space directions")
    if directions:
        vectors = _vectors(path, "space directions", directions)
        steps = np.array([vectors[a] for a in spatial], float).T
        if not header.get("space"):
            notes.append("`space directions` without `space`: axes taken as LPS")
    else:
        steps = np.diag(_spacings(header, spatial, notes))
        if header.get("space"):
            notes.append(
                "the header mixed `space` with `spacings` (no `space directions`); the "
                "spacings were read as axis-aligned steps"
            )
        else:
            notes.append("no `space` field: axes taken as LPS-aligned with the spacings")
    affine = np.eye(4)
    with np.errstate(all="ignore"):  # inf/NaN in the header: make_volume refuses the result
        affine[:3, :3] = np.diag(flips) @ steps
        affine[:3, 3] = np.diag(flips) @ _origin(path, header, spatial)
    return affine


def _space_flips(space: str | None, notes: list[str]) -> tuple[int, int, int]:
    if space is None:
        return (1, 1, 1)
    name = re.sub(r"(-time|t)$", "", space.strip().lower())
    if name in SPACES:
        return SPACES[name]
    notes.append(f"space '{space}' has no anatomical orientation: axes taken as LPS")
    return (1, 1, 1)


def _spacings(header: NrrdHeader, spatial: list[int], notes: list[str]) -> list[float]:
    values = [_number(v) for v in (header.get("spacings") or "").split()]
    steps = [values[a] if a < len(values) else np.nan for a in spatial]
    if any(not np.isfinite(s) or s == 0 for s in steps):
        notes.append("no usable `spacings`: 1 mm assumed where missing")
    return [s if np.isfinite(s) and s != 0 else 1.0 for s in steps]


def _origin(path: Path, header: NrrdHeader, spatial: list[int]) -> np.ndarray:
    if header.get("space origin"):
        vectors = _vectors(path, "space origin", header.get("space origin") or "")
        if len(vectors) != 1 or vectors[0] is None:
            raise UnreadableVolume(
                f"{path.name}: bad NRRD header: 'space origin' must be one vector like "
                "(0,0,0); fix that line."
            )
        return np.array(vectors[0], float)
    mins = (header.get("axis mins") or "").split()
    if len(mins) == len(header.sizes):
        return np.nan_to_num(np.array([_number(mins[a]) for a in spatial]))
    return np.zeros(3)


def _number(text: str) -> float:
    """A float, or NaN for text that is not one (``nan`` and unparsable alike)."""
    try:
        return float(text)
    except ValueError:
        return float("nan")


def _vectors(path: Path, field: str, text: str) -> list[list[float] | None]:
    """Parse ``(1,0,0) (0,1,0) none`` into 3-vectors (None for ``none``)."""
    found = re.findall(r"\(([^)]*)\)|(none)", text)
    try:
        vectors = [None if word else [float(v) for v in vec.split(",")] for vec, word in found]
    except ValueError as exc:
        raise UnreadableVolume(
            f"{path.name}: bad NRRD header: '{field}' holds something that is not a number "
            f"({exc}); fix that line."
        ) from exc
    if any(v is not None and len(v) != 3 for v in vectors):
        raise UnreadableVolume(
            f"{path.name}: bad NRRD header: '{field}' needs 3-D vectors like (1,0,0) for a "
            "3-D space; fix that line."
        )
    return vectors


def data_file_named(path: Path) -> str:
    """The ``data file`` a NRRD header names ("" when the data is attached)."""
    with path.open("rb") as stream:
        return nrrd_header.data_file_spec(stream.read(nrrd_header.HEADER_LIMIT))
