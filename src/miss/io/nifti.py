"""NIfTI-1/2 reader (``.nii``, ``.nii.gz``) through nibabel.

nibabel's ``img.affine`` (sform, else qform, else voxel sizes) maps to RAS; MISS works
in LPS, so its first two rows are negated. Scaling (scl_slope/scl_inter) is applied
only when it is not the identity, so label maps and raw CTs keep their integer dtype.
"""

from __future__ import annotations

import gzip
import io
import logging
import math
import struct
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

import numpy as np

from miss.errors import UnreadableVolume
from miss.io.common import (
    DEFLATE_MAX_RATIO,
    RAS_TO_LPS,
    check_declared_size,
    finite_values,
    integer_dtype,
    make_volume,
    no_series,
    recorded_warnings,
)
from miss.types import Volume

if TYPE_CHECKING:
    import nibabel as nib

# nibabel (0.2 s to load) is imported by the functions that read: ``sniff`` and the other
# formats never load it.
NIFTI1_MAGICS = (b"n+1\0", b"ni1\0")
NIFTI2_MAGICS = (b"n+2\0", b"ni2\0")
GZIP_MAGIC = b"\x1f\x8b"
#: sizeof_hdr, the first 4 bytes of a NIfTI-1 (348) or NIfTI-2 (540) header, either byte order.
SIZEOF_HDR = {struct.pack(e + "i", n) for e in "<>" for n in (348, 540)}
#: (dim format, dim offset, datatype offset, vox_offset format, vox_offset offset).
NIFTI1_LAYOUT = ("8h", 40, 70, "f", 108)
NIFTI2_LAYOUT = ("8q", 16, 12, "q", 168)
#: Errors a damaged gzip stream raises while nibabel reads it.
TRUNCATION_ERRORS = (EOFError, zlib.error, gzip.BadGzipFile)


def sniff(path: Path, head: bytes) -> bool:
    """``.nii``/``.nii.gz`` names, or NIfTI magic in an uncompressed header."""
    name = path.name.lower()
    return name.endswith((".nii", ".nii.gz")) or _magic_ok(head)


def read(path: Path, series: str | None) -> Volume:
    """Read a NIfTI volume; see the module docstring for scaling and orientation."""
    from nibabel.filebasedimages import ImageFileError
    from nibabel.spatialimages import HeaderDataError

    no_series(path, series, "NIfTI")
    declared = _check_header(path)
    try:
        with _nibabel_notes() as said:
            img = _load(path, declared)
            data, notes = _voxels(path, img)
            affine = img.affine
    except (*TRUNCATION_ERRORS, OSError) as exc:  # nibabel: "Expected 240 bytes, got 191"
        raise _truncated(path, _first_line(exc)) from exc
    except (ImageFileError, HeaderDataError) as exc:
        raise UnreadableVolume(
            f"{path.name}: nibabel cannot read this NIfTI header ({_first_line(exc)}); re-export "
            "the volume from the program that wrote it."
        ) from exc
    notes += said + _orientation_notes(img)
    slope, inter = _scaling(img)
    description = _description(img)
    ct = _looks_like_ct(data, description)
    if ct:
        notes.append("values read as CT Hounsfield units (" + ct + ")")
    with np.errstate(all="ignore"):  # inf in a damaged header: make_volume refuses it
        affine = RAS_TO_LPS @ affine
    return make_volume(
        path,
        data,
        affine,
        "nifti",
        notes=notes,
        rescale=(slope, inter),
        series_description=description,
        **({"modality": "CT", "units": "HU"} if ct else {}),
    )


class _Collect(logging.Handler):
    def __init__(self) -> None:
        super().__init__()
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


@contextmanager
def _nibabel_notes() -> Iterator[list[str]]:
    """What nibabel logs (``pixdim[1,2,3] should be non-zero; setting 0 dims to 1``) and
    warns about, as notes instead of stray lines on stderr. Filled when the block ends."""
    from nibabel import imageglobals

    logger = imageglobals.logger
    handlers, collect = logger.handlers[:], _Collect()
    for handler in handlers:
        logger.removeHandler(handler)
    logger.addHandler(collect)
    said: list[str] = []
    try:
        with recorded_warnings("nibabel") as warned:
            yield said
    finally:
        logger.removeHandler(collect)
        for handler in handlers:
            logger.addHandler(handler)
        said.extend(dict.fromkeys(f"nibabel: {m}" for m in collect.messages))
        said.extend(warned)


def _load(path: Path, declared: Declared) -> nib.Nifti1Image:
    """``nib.load``, or (when the name says .gz and the bytes do not, or the other way
    round) the same image read through the opener the content needs."""
    import nibabel as nib

    if path.name.lower().endswith(".gz") == _gzipped(path) or declared.pair:
        return nib.load(path, mmap=False)
    klass = nib.Nifti2Image if declared.version == 2 else nib.Nifti1Image
    with _open(path) as stream:
        content = io.BytesIO(stream.read(declared.needed))
    holder = nib.FileHolder(filename=str(path), fileobj=content)
    return klass.from_file_map({"image": holder, "header": holder}, mmap=False)


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


@dataclass(frozen=True)
class Declared:
    """What a NIfTI header declares, checked for sense before nibabel reads it."""

    version: int  # 1 or 2
    pair: bool  # .hdr/.img pair (magic ni1/ni2): the voxels live in the .img
    shape: tuple[int, ...]  # dim[1] .. dim[dim[0]]
    dtype: np.dtype
    vox_offset: float

    @property
    def needed(self) -> int:
        """Bytes from the start of the file to the end of the voxels."""
        return int(self.vox_offset) + math.prod(self.shape) * self.dtype.itemsize


def _check_header(path: Path) -> Declared:
    """Tell truncated, mislabelled and impossible headers apart before nibabel's generic errors.

    Sizes are checked against the bytes present (and a voxel cap) here, so a header that
    declares 100000^3 voxels is refused before anything is allocated or inflated.
    """
    try:
        with _open(path) as stream:
            header = stream.read(548)
    except (*TRUNCATION_ERRORS, OSError) as exc:
        raise _truncated(path, str(exc)) from exc
    if not _magic_ok(header):
        if len(header) < 348 and header[:4] in SIZEOF_HDR:
            raise _truncated(path, f"the header stops after {len(header)} of 348 bytes")
        raise UnreadableVolume(
            f"{path.name}: not a NIfTI file: no 'n+1' magic at byte 344 (found "
            f"{header[344:348]!r}); check it was not renamed from another format or damaged."
        )
    declared = _declared(path, header)
    _check_size(path, declared)
    return declared


def _declared(path: Path, header: bytes) -> Declared:
    """Parse dim, datatype and vox_offset (NIfTI-1 or -2, either byte order) and check them."""
    from nibabel.nifti1 import data_type_codes

    version = 2 if header[4:8] in NIFTI2_MAGICS else 1
    if version == 2 and len(header) < 540:
        raise _truncated(path, f"the NIfTI-2 header stops after {len(header)} of 540 bytes")
    size, layout = (540, NIFTI2_LAYOUT) if version == 2 else (348, NIFTI1_LAYOUT)
    endian = "<" if struct.unpack("<i", header[:4])[0] == size else ">"
    dim_fmt, dim_at, code_at, offset_fmt, offset_at = layout
    dim = struct.unpack_from(endian + dim_fmt, header, dim_at)
    code = struct.unpack_from(endian + "h", header, code_at)[0]
    vox_offset = float(struct.unpack_from(endian + offset_fmt, header, offset_at)[0])
    bad = f"{path.name}: bad NIfTI header:"
    fix = "re-export the volume from the program that wrote it."
    if not 1 <= dim[0] <= 7:
        raise UnreadableVolume(f"{bad} dim[0] = {dim[0]} is not a dimension count (1 to 7); {fix}")
    shape = tuple(int(n) for n in dim[1 : 1 + dim[0]])
    if min(shape) < 1:
        raise UnreadableVolume(f"{bad} the sizes {list(shape)} must all be positive; {fix}")
    if code not in data_type_codes.value_set():
        raise UnreadableVolume(f"{bad} datatype code {code} is not a NIfTI type; {fix}")
    dtype = data_type_codes.dtype[code]
    if dtype.kind not in "iuf":
        name = data_type_codes.label[code]
        raise UnreadableVolume(
            f"{path.name}: its voxels are of NIfTI type {name!r}, not one real number each "
            "(MISS draws density surfaces); convert it to a greyscale (scalar) volume first."
        )
    if not np.isfinite(vox_offset) or vox_offset < 0:
        raise UnreadableVolume(f"{bad} vox_offset {vox_offset} is not a byte offset; {fix}")
    pair = header[344:348] == b"ni1\0" or header[4:8] == b"ni2\0"
    return Declared(version, pair, shape, dtype, vox_offset)


def _check_size(path: Path, declared: Declared) -> None:
    """Header sizes against the voxel cap and the bytes (or compressed bytes) on disk."""
    data_path = path.with_suffix(".img") if declared.pair else path
    if not data_path.is_file():
        raise UnreadableVolume(
            f"{path.name}: a NIfTI header whose voxels live in {data_path.name}, which is not "
            "there; put the .img beside the .hdr."
        )
    on_disk = data_path.stat().st_size
    gz = _gzipped(data_path)
    check_declared_size(path, declared.shape, declared.dtype.itemsize, on_disk if gz else None)
    if not gz and on_disk < declared.needed:
        raise _truncated(path, f"it has {on_disk} bytes, the header needs {declared.needed}")
    if gz and declared.needed > DEFLATE_MAX_RATIO * on_disk:  # vox_offset can be absurd too
        raise _truncated(
            path, f"the header needs {declared.needed} bytes; {on_disk} compressed cannot hold them"
        )


def _open(path: Path) -> BinaryIO:
    return gzip.open(path, "rb") if _gzipped(path) else path.open("rb")


def _gzipped(path: Path) -> bool:
    with path.open("rb") as stream:
        return stream.read(2) == GZIP_MAGIC


def _magic_ok(header: bytes) -> bool:
    return header[344:348] in NIFTI1_MAGICS or header[4:8] in NIFTI2_MAGICS


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


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
            "3-D volume with at least 2 slices: pass the whole scan instead."
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
    return finite_values(path, values, notes), notes


def _orientation_notes(img: nib.Nifti1Image) -> list[str]:
    header = img.header
    if int(header["sform_code"]) == 0 and int(header["qform_code"]) == 0:
        return ["no sform or qform: orientation unknown, axes taken as RAS with the voxel sizes"]
    return []


def _description(img: nib.Nifti1Image) -> str:
    raw = img.header["descrip"].item()
    return raw.decode("latin-1").strip("\0 ") if isinstance(raw, bytes) else str(raw)
