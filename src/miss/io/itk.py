"""SimpleITK as the catch-all reader, and the SimpleITK image -> ``Volume`` conversion.

ITK keeps geometry in LPS already (origin, spacing, direction cosines), so no axis
flips are needed. Anything ITK's image IO factory recognises (Analyze, VTK legacy,
MINC, GIPL, ...) ends up here when no dedicated reader claims it.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from miss.errors import UnreadableVolume, UnsupportedFormat
from miss.io import codecs
from miss.io.common import affine_from, check_declared_size, make_volume, no_series, zyx_to_xyz
from miss.types import Volume

if TYPE_CHECKING:
    import SimpleITK as sitk

#: Values per byte on disk beyond which a header for the catch-all formats is refused.
#: Far above what real compression reaches (DEFLATE ~1000:1; LZW on empty masks more):
#: it only stops headers that declare terabytes in a few kilobytes.
MAX_RATIO = 100_000


def _simpleitk() -> ModuleType:
    """SimpleITK (0.1 s to load: only when a file gets this far), its warnings off.

    ITK prints its warnings ("unexpected scales in sform") straight to stderr, which would
    put stray lines before the CLI's one-line message; MISS reports through notes instead.
    """
    import SimpleITK

    SimpleITK.ProcessObject.SetGlobalWarningDisplay(False)
    return SimpleITK


def sniff(path: Path, head: bytes) -> bool:
    """Files for which ITK's IO factory finds an image reader."""
    if path.is_dir():
        return False
    try:
        return bool(_simpleitk().ImageFileReader().GetImageIOFromFileName(str(path)))
    except RuntimeError:
        return False


def read(path: Path, series: str | None) -> Volume:
    """Read any image SimpleITK can; its errors become ``UnsupportedFormat``."""
    no_series(path, series, "non-DICOM")
    return to_volume(path, read_image(path, on_disk=_bytes_beside(path)), "itk")


def read_image(path: Path, on_disk: int | None = None) -> sitk.Image:
    """``sitk.ReadImage`` with ITK's multi-line exception text cut to its message.

    The header is read first and its size checked (``MAX_VOXELS``; and, given the bytes
    ``on_disk`` that can hold the voxels, ``MAX_RATIO``), so an absurd header is refused
    before ITK allocates the image.
    """
    reader = _simpleitk().ImageFileReader()
    reader.SetFileName(str(path))
    try:
        reader.ReadImageInformation()
        shape = [*reader.GetSize(), reader.GetNumberOfComponents()]
        check_declared_size(path, shape, 1)
        if on_disk is not None:
            _check_on_disk(path, reader, shape, on_disk)
        return reader.Execute()
    except RuntimeError as exc:
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        reason = _without_addresses(lines[-1]) if lines else "unknown error"
        raise UnsupportedFormat(f"SimpleITK cannot read {path.name} ({reason})") from exc


def _check_on_disk(
    path: Path, reader: sitk.ImageFileReader, shape: list[int], on_disk: int
) -> None:
    """The declared image against the ``on_disk`` bytes that hold it, before ITK decodes:
    the caps of :mod:`miss.io.codecs`, whatever codec the format uses (TIFF's LZW,
    MINC's HDF5 gzip, .mgz ...), and ``MAX_RATIO`` values per byte below them."""
    if math.prod(shape) > MAX_RATIO * on_disk:
        raise UnreadableVolume(
            f"{path.name}: the header declares {'x'.join(map(str, shape))} values, which "
            f"{on_disk} bytes on disk cannot hold; the header is damaged: fix its sizes."
        )
    sitk = _simpleitk()
    itemsize = sitk.Image([1, 1], reader.GetPixelID()).GetSizeOfPixelComponent()
    what = f"{'x'.join(map(str, shape[:-1]))} x {shape[-1]} component(s) of {itemsize} byte(s)"
    codecs.check_decoded(path, math.prod(shape) * itemsize, on_disk, "file data", what)


def folder_bytes(path: Path) -> int:
    """Bytes of the regular files in ``path``'s folder: all a header there may name."""
    return sum(p.stat().st_size for p in path.parent.iterdir() if p.is_file())


def _bytes_beside(path: Path) -> int:
    """Bytes of the file and its companions sharing its stem (``x.hdr`` + ``x.img``)."""
    stem = path.name.split(".")[0]
    return sum(
        p.stat().st_size
        for p in path.parent.iterdir()
        if p.is_file() and p.name.split(".")[0] == stem
    )


def _without_addresses(text: str) -> str:
    """ITK's messages name C++ objects by address (``NiftiImageIO(0x55d6...)``): drop those."""
    return re.sub(r"\(0x[0-9a-fA-F]+\)", "", text)


def to_volume(
    path: Path, image: sitk.Image, source_format: str, notes: Sequence[str] = ()
) -> Volume:
    """Convert a SimpleITK image to a ``Volume`` (first component, first time point)."""
    notes = list(notes)
    dim = image.GetDimension()
    # A copy, not GetArrayViewFromImage: views of ITK's buffer were seen to go stale.
    zyx = _simpleitk().GetArrayFromImage(image)
    if image.GetNumberOfComponentsPerPixel() > 1:
        notes.append(
            f"{image.GetNumberOfComponentsPerPixel()} components per voxel: read the first"
        )
        zyx = zyx[..., 0]
    if dim > 3:
        notes.append(f"{dim}-D image of size {image.GetSize()}: read the first volume")
        zyx = zyx[(0,) * (dim - 3)]
    zyx = np.ascontiguousarray(zyx)  # a no-op unless a component or volume was picked
    if dim < 3:  # make_volume rejects it with a message that names the shape
        return make_volume(path, zyx.T, np.eye(4), source_format, notes=notes)
    direction = np.array(image.GetDirection(), float).reshape(dim, dim)[:3, :3]
    affine = affine_from(direction, image.GetSpacing()[:3], image.GetOrigin()[:3])
    return make_volume(path, zyx_to_xyz(zyx), affine, source_format, notes=notes)
