"""Read a CT/MR volume from whatever the user has: DICOM, NIfTI, NRRD, MetaImage ...

``load_volume`` checks the path once, sniffs the first bytes, and asks each reader in
``READERS`` (in order) whether the file is its own. Every reader module has the same
small contract::

    sniff(path: Path, head: bytes) -> bool   # is this mine? (extension, magic bytes)
    read(path: Path, series: str | None) -> Volume

A reader that recognises its format but finds it broken raises ``UnreadableVolume``
with the diagnosis, which is final. Any other failure lets the next reader try; when
all fail, one ``UnreadableVolume`` lists why each one did.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from miss.errors import MissError, UnreadableVolume, UnsupportedFormat
from miss.io import dicom, itk, metaimage, nifti, nrrd
from miss.io.common import Streamed
from miss.types import Volume

#: Tried in this order; ``itk`` is the catch-all for anything else SimpleITK reads.
READERS = [dicom, nifti, nrrd, metaimage, itk]

#: Enough bytes for every magic number we look at (DICOM's sits at 128, NIfTI's at 344).
HEAD_BYTES = 1024


#: Formats whose headers can name other files: MISS's own parser decides what they read,
#: so once one of these readers has claimed a file, SimpleITK is not asked to try it.
NAMES_OTHER_FILES = (nrrd, metaimage)


def load_volume(path: str | os.PathLike[str], series: str | None = None) -> Volume:
    """Read a scan into a ``Volume`` (LPS millimetres, real units).

    Parameters
    ----------
    path : str or PathLike
        A DICOM folder, ``.zip`` or file; ``.nii``/``.nii.gz``; ``.nrrd``/``.nhdr``;
        ``.mha``/``.mhd``; or another format SimpleITK reads.
    series : str, optional
        DICOM SeriesInstanceUID to read when several are present (default: the one
        with the most slices). See :func:`list_series`.

    Raises
    ------
    UnreadableVolume
        Missing, empty, truncated or damaged input; the message names the fix.
    UnsupportedFormat
        No reader recognises the file.
    BadParameter
        ``series`` names no series in the input.
    """
    p = _existing(path)
    head = _head(p)
    failures: list[str] = []
    claimed = False
    for reader in READERS:
        if not reader.sniff(p, head) or (reader is itk and claimed):
            continue
        claimed = claimed or reader in NAMES_OTHER_FILES
        try:
            return reader.read(p, series)
        except UnsupportedFormat as exc:  # a variant this reader lacks: let the next try
            failures.append(f"{_name(reader)}: {exc}")
        except MissError:  # a diagnosis (broken file, bad series=): final
            raise
        except Exception as exc:  # library internals: report, let the next reader try
            failures.append(f"{_name(reader)}: {_first_line(exc)}")
    raise _all_failed(p, failures)


def stream_volume(path: str | os.PathLike[str], series: str | None = None) -> Streamed | None:
    """What :func:`load_volume` would read at ``path``, as planes read one at a time, when
    the reader it picks can stream it: a folder of DICOM slices (:func:`dicom.stream`) or
    a plain NIfTI-1 file (:func:`nifti.stream`); None when it reads the volume whole.

    The same voxels, dtype, affine, metadata and patient as ``load_volume``. A file it
    would refuse may raise here with another message: read it whole then, to say why.
    """
    p = Path(path)
    if p.is_dir():
        return dicom.stream(p, series)
    if series is not None or not p.is_file() or p.stat().st_size == 0:
        return None  # NIfTI refuses ``series``; an empty file: load_volume says so
    head = _head(p)
    if dicom.sniff(p, head) or not nifti.sniff(p, head):
        return None  # DICOM is tried first there, and only a folder of it streams
    return nifti.stream(p)


def list_series(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Series found at ``path``: [{"uid", "description", "modality", "slices", "dims"}].

    ``dims`` is (columns, rows, slices). Non-DICOM inputs hold one volume and give a
    one-entry list (read in full to describe it).
    """
    p = _existing(path)
    if dicom.sniff(p, _head(p)):
        try:
            return dicom.list_series(p)
        except MissError:
            raise
        except Exception as exc:
            raise UnreadableVolume(
                f"{p.name}: cannot list DICOM series ({_first_line(exc)})."
            ) from exc
    return load_volume(p).meta["series"]


def self_contained(path: str | os.PathLike[str]) -> str:
    """Why ``path`` could make a reader open other files ("" when it cannot): a detached
    NRRD or MetaImage header, or a format only SimpleITK's catch-all reads (some of those,
    HDF5 and MINC among them, can link to other files)."""
    p = _existing(path)
    head = _head(p)
    if p.is_dir() or dicom.sniff(p, head) or nifti.sniff(p, head):
        return ""
    if nrrd.sniff(p, head):
        named = nrrd.data_file_named(p)
        return f"{p.name} is a detached NRRD header (data file: {named})" if named else ""
    if metaimage.sniff(p, head):
        named = metaimage.data_file_named(p)
        return f"{p.name} is a MetaImage header with ElementDataFile {named}" if named else ""
    return f"{p.name} is not DICOM, NIfTI, NRRD or MetaImage"


def _existing(path: str | os.PathLike[str]) -> Path:
    """The path, checked to exist and (for a file) to be non-empty."""
    p = Path(path)
    if not p.exists():
        raise UnreadableVolume(f"{p}: no such file or folder; check the path.")
    if p.is_file() and p.stat().st_size == 0:
        raise UnreadableVolume(
            f"{p.name}: the file is empty (0 bytes); the upload or copy was probably "
            "interrupted, copy it again."
        )
    return p


def _head(path: Path) -> bytes:
    if path.is_dir():
        return b""
    try:
        with path.open("rb") as stream:
            return stream.read(HEAD_BYTES)
    except OSError as exc:
        raise UnreadableVolume(
            f"{path.name}: cannot be opened ({exc.strerror}); check its permissions."
        ) from exc


def _all_failed(path: Path, failures: list[str]) -> MissError:
    if not failures:
        return UnsupportedFormat(
            f"{path.name}: not a format MISS reads. Use a DICOM folder/.zip/.dcm, NIfTI "
            "(.nii, .nii.gz), NRRD (.nrrd, .nhdr), MetaImage (.mha, .mhd) or another "
            "format SimpleITK reads."
        )
    return UnreadableVolume(
        f"{path.name}: no reader could read it ({'; '.join(failures)}); check that it is a "
        "complete, undamaged scan file, or copy it again."
    )


def _name(reader: Any) -> str:
    return reader.__name__.rsplit(".", 1)[-1]


def _first_line(exc: BaseException) -> str:
    """The exception's first line, or a plain phrase when it has no message."""
    text = str(exc).strip()
    if text:
        return text.splitlines()[0]
    return "not enough memory" if isinstance(exc, MemoryError) else "an internal error"


__all__ = ["READERS", "list_series", "load_volume", "self_contained", "stream_volume"]
