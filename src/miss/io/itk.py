"""SimpleITK as the catch-all reader, and the SimpleITK image -> ``Volume`` conversion.

ITK keeps geometry in LPS already (origin, spacing, direction cosines), so no axis
flips are needed. Anything ITK's image IO factory recognises (Analyze, VTK legacy,
MINC, GIPL, ...) ends up here when no dedicated reader claims it.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import SimpleITK as sitk

from miss.errors import UnsupportedFormat
from miss.io.common import affine_from, make_volume, no_series, zyx_to_xyz
from miss.types import Volume


def sniff(path: Path, head: bytes) -> bool:
    """Files for which ITK's IO factory finds an image reader."""
    if path.is_dir():
        return False
    try:
        return bool(sitk.ImageFileReader().GetImageIOFromFileName(str(path)))
    except RuntimeError:
        return False


def read(path: Path, series: str | None) -> Volume:
    """Read any image SimpleITK can; its errors become ``UnsupportedFormat``."""
    no_series(path, series, "non-DICOM")
    return to_volume(path, read_image(path), "itk")


def read_image(path: Path) -> sitk.Image:
    """``sitk.ReadImage`` with ITK's multi-line exception text cut to its message."""
    try:
        return sitk.ReadImage(str(path))
    except RuntimeError as exc:
        lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
        reason = lines[-1] if lines else "unknown error"
        raise UnsupportedFormat(f"SimpleITK cannot read {path.name} ({reason})") from exc


def to_volume(
    path: Path, image: sitk.Image, source_format: str, notes: Sequence[str] = ()
) -> Volume:
    """Convert a SimpleITK image to a ``Volume`` (first component, first time point)."""
    notes = list(notes)
    dim = image.GetDimension()
    # A copy, not GetArrayViewFromImage: views of ITK's buffer were seen to go stale.
    zyx = sitk.GetArrayFromImage(image)
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
