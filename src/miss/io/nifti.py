"""NIfTI-1/2 reader (``.nii``, ``.nii.gz``) through nibabel.

nibabel's ``img.affine`` (sform, else qform, else voxel sizes) maps to RAS; MISS works
in LPS, so its first two rows are negated. Scaling (scl_slope/scl_inter) is applied
only when it is not the identity, so label maps and raw CTs keep their integer dtype.
"""

from __future__ import annotations

import gzip
import struct
import zlib
from pathlib import Path
from typing import BinaryIO

import nibabel as nib
import numpy as np

from miss.errors import UnreadableVolume
from miss.io.common import RAS_TO_LPS, integer_dtype, make_volume, no_series
from miss.types import Volume

NIFTI1_MAGICS = (b"n+1\0", b"ni1\0")
NIFTI2_MAGICS = (b"n+2\0", b"ni2\0")
GZIP_MAGIC = b"\x1f\x8b"
#: Errors a damaged gzip stream raises while nibabel reads it.
TRUNCATION_ERRORS = (EOFError, zlib.error, gzip.BadGzipFile)


def sniff(path: Path, head: bytes) -> bool:
    """``.nii``/``.nii.gz`` names, or NIfTI magic in an uncompressed header."""
    name = path.name.lower()
    return name.endswith((".nii", ".nii.gz")) or _magic_ok(head)


def read(path: Path, series: str | None) -> Volume:
    """Read a NIfTI volume; see the module docstring for scaling and orientation."""
    no_series(path, series, "NIfTI")
    _check_header(path)
    try:
        img = nib.load(path, mmap=False)
        data, notes = _voxels(path, img)
    except TRUNCATION_ERRORS as exc:
        raise _truncated(path, str(exc)) from exc
    notes += _orientation_notes(img)
    slope, inter = _scaling(img)
    description = _description(img)
    ct = _looks_like_ct(data, description)
    if ct:
        notes.append("values read as CT Hounsfield units (" + ct + ")")
    return make_volume(
        path,
        data,
        RAS_TO_LPS @ img.affine,
        "nifti",
        notes=notes,
        rescale=(slope, inter),
        series_description=description,
        **({"modality": "CT", "units": "HU"} if ct else {}),
    )


def _looks_like_ct(data: np.ndarray, description: str) -> str:
    """Why the volume is taken as CT in HU ('' when it is not).

    NIfTI has no modality field, but bone and skin presets need to know HU: trust a
    description that says so, else air at about -1000 (or a -2048/-3024 pad) with tissue above 0 is CT.
    """
    words = description.upper().split()
    if "HU" in words or "CT" in words:
        return f"the header description says {description!r}"
    lo, hi = float(np.min(data)), float(np.max(data))
    if -3100.0 <= lo <= -900.0 and hi > 100.0:  # some scanners pad outside the FOV at -2048/-3024
        return f"air at {lo:g}, as CT stores it"
    return ""


def _check_header(path: Path) -> None:
    """Tell a truncated or mislabelled file apart before nibabel's generic errors."""
    try:
        with _open(path) as stream:
            header = stream.read(548)
    except (*TRUNCATION_ERRORS, OSError) as exc:
        raise _truncated(path, str(exc)) from exc
    if len(header) < 348:
        raise _truncated(path, f"the header stops after {len(header)} of 348 bytes")
    if not _magic_ok(header):
        raise UnreadableVolume(
            f"{path.name}: not a NIfTI file: no 'n+1' magic at byte 344 (found "
            f"{header[344:348]!r}); check it was not renamed from another format or damaged."
        )
    if _gzipped(path):
        return
    needed = _expected_bytes(header)
    if needed and path.stat().st_size < needed:
        raise _truncated(path, f"it has {path.stat().st_size} bytes, the header needs {needed}")


def _open(path: Path) -> BinaryIO:
    return gzip.open(path, "rb") if _gzipped(path) else path.open("rb")


def _gzipped(path: Path) -> bool:
    with path.open("rb") as stream:
        return stream.read(2) == GZIP_MAGIC


def _magic_ok(header: bytes) -> bool:
    return header[344:348] in NIFTI1_MAGICS or header[4:8] in NIFTI2_MAGICS


def _expected_bytes(header: bytes) -> int:
    """vox_offset + voxel bytes from a NIfTI-1 header (0 when it cannot tell)."""
    if header[344:348] != b"n+1\0":  # NIfTI-2 and .hdr/.img pairs: leave it to nibabel
        return 0
    endian = "<" if struct.unpack("<i", header[:4])[0] == 348 else ">"
    dims = struct.unpack(endian + "8h", header[40:56])
    bitpix = struct.unpack(endian + "h", header[72:74])[0]
    vox_offset = struct.unpack(endian + "f", header[108:112])[0]
    count = int(np.prod([max(d, 1) for d in dims[1 : 1 + max(dims[0], 0)]], dtype=np.int64))
    return int(vox_offset) + count * bitpix // 8


def _truncated(path: Path, detail: str) -> UnreadableVolume:
    return UnreadableVolume(
        f"{path.name}: the file is truncated or damaged ({detail}); copy or download it again."
    )


def _scaling(img: nib.Nifti1Image) -> tuple[float, float]:
    """(slope, intercept) nibabel will apply; (1, 0) when the header asks for none."""
    slope = getattr(img.dataobj, "slope", 1.0)
    inter = getattr(img.dataobj, "inter", 0.0)
    slope = 1.0 if slope is None or not np.isfinite(slope) or slope == 0 else float(slope)
    inter = 0.0 if inter is None or not np.isfinite(inter) else float(inter)
    return slope, inter


def _voxels(path: Path, img: nib.Nifti1Image) -> tuple[np.ndarray, list[str]]:
    """(X, Y, Z) voxels in real units: first volume of a 4-D+ image, NaN/Inf replaced."""
    notes: list[str] = []
    if len(img.shape) > 3 and int(np.prod(img.shape[3:])) > 1:
        notes.append(f"image is {'x'.join(map(str, img.shape))}: read only the first volume")
    if len(img.shape) < 3:
        raise UnreadableVolume(
            f"{path.name}: a {len(img.shape)}-D image of shape {img.shape}; a surface needs a "
            "3-D volume with at least 2 slices."
        )
    # Slicing the proxy reads one volume and applies scl_slope/inter only when they are
    # not the identity, so unscaled images keep their stored dtype.
    values = np.asarray(img.dataobj[(slice(None),) * 3 + (0,) * (len(img.shape) - 3)])
    slope, inter = _scaling(img)
    if (slope, inter) != (1.0, 0.0):
        integral = img.get_data_dtype().kind in "iu" and slope.is_integer() and inter.is_integer()
        if integral:
            values = values.astype(integer_dtype((int(values.min()), int(values.max())), 1.0, 0.0))
        else:
            values = values.astype(np.float32, copy=False)
    return _finite(path, values, notes), notes


def _finite(path: Path, values: np.ndarray, notes: list[str]) -> np.ndarray:
    """Replace NaN by the smallest finite value and +/-Inf by the extreme finite values."""
    if values.dtype.kind != "f" or np.isfinite(values).all():
        return values
    finite = values[np.isfinite(values)]
    if finite.size == 0:
        raise UnreadableVolume(
            f"{path.name}: every voxel is NaN or infinite; there is nothing to draw."
        )
    lo, hi = finite.min(), finite.max()
    notes.append(
        f"replaced {int(np.isnan(values).sum())} NaN voxel(s) by the minimum {lo:g} and "
        f"{int(np.isinf(values).sum())} infinite voxel(s) by the finite extremes"
    )
    return np.nan_to_num(values, nan=lo, posinf=hi, neginf=lo)


def _orientation_notes(img: nib.Nifti1Image) -> list[str]:
    header = img.header
    if int(header["sform_code"]) == 0 and int(header["qform_code"]) == 0:
        return ["no sform or qform: orientation unknown, axes taken as RAS with the voxel sizes"]
    return []


def _description(img: nib.Nifti1Image) -> str:
    raw = img.header["descrip"].item()
    return raw.decode("latin-1").strip("\0 ") if isinstance(raw, bytes) else str(raw)
