"""The NIfTI-1/2 header, read and checked by MISS before anything reads the voxels.

:func:`check_header` tells truncated, mislabelled and impossible files apart (with their
own messages) and refuses sizes the bytes on disk cannot hold. :meth:`Declared.plain`
says whether MISS's own reader reads the voxels (:mod:`miss.io.nifti`): a single-file
NIfTI-1 volume with an sform, no scaling and nothing nibabel would warn about; the rest
goes to nibabel.
"""

from __future__ import annotations

import gzip
import io
import math
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from miss.errors import UnreadableVolume
from miss.io import codecs
from miss.io.common import DEFLATE_MAX_RATIO, check_declared_size

NIFTI1_MAGICS = (b"n+1\0", b"ni1\0")
NIFTI2_MAGICS = (b"n+2\0", b"ni2\0")
GZIP_MAGIC = b"\x1f\x8b"
#: sizeof_hdr, the first 4 bytes of a NIfTI-1 (348) or NIfTI-2 (540) header, either byte order.
SIZEOF_HDR = {struct.pack(e + "i", n) for e in "<>" for n in (348, 540)}
#: (dim format, dim offset, datatype offset, vox_offset format, vox_offset offset).
NIFTI1_LAYOUT = ("8h", 40, 70, "f", 108)
NIFTI2_LAYOUT = ("8q", 16, 12, "q", 168)
#: Errors a damaged gzip stream raises while it is read.
TRUNCATION_ERRORS = (EOFError, zlib.error, gzip.BadGzipFile)
#: NIfTI datatype codes: nibabel's name for each, and its numpy type when a voxel is one
#: real number (float128 is not: nibabel reads it only where longdouble is IEEE binary128).
DATATYPES: dict[int, tuple[str, str | None]] = {
    0: ("none", None), 1: ("binary", None), 2: ("uint8", "u1"), 4: ("int16", "i2"),
    8: ("int32", "i4"), 16: ("float32", "f4"), 32: ("complex64", None), 64: ("float64", "f8"),
    128: ("RGB", None), 255: ("all", None), 256: ("int8", "i1"), 512: ("uint16", "u2"),
    768: ("uint32", "u4"), 1024: ("int64", "i8"), 1280: ("uint64", "u8"),
    1536: ("float128", None), 1792: ("complex128", None), 2048: ("complex256", None),
    2304: ("RGBA", None),
}  # fmt: skip
#: sform_code and qform_code values nibabel knows (unknown .. template).
XFORM_CODES = range(6)


@dataclass(frozen=True)
class Declared:
    """What a NIfTI header declares, checked for sense; ``head`` is its first bytes."""

    version: int  # 1 or 2
    pair: bool  # .hdr/.img pair (magic ni1/ni2): the voxels live in the .img
    shape: tuple[int, ...]  # dim[1] .. dim[dim[0]]
    dtype: np.dtype  # native byte order
    vox_offset: float
    endian: Literal["<", ">"]
    head: bytes

    @property
    def needed(self) -> int:
        """Bytes from the start of the file to the end of the voxels."""
        return int(self.vox_offset) + math.prod(self.shape) * self.dtype.itemsize

    def field(self, fmt: str, at: int) -> tuple[float, ...]:
        """NIfTI-1 header values at byte ``at`` (struct format without byte order)."""
        return struct.unpack_from(self.endian + fmt, self.head, at)

    @property
    def plain(self) -> bool:
        """MISS reads the voxels itself: one .nii(.gz) file, NIfTI-1, 3-D, an sform, no
        scaling, no extensions, and none of the header problems nibabel logs (sizeof_hdr,
        bitpix, pixdim, qfac, offset, form codes), so nothing it would say is lost."""
        if self.version != 1 or self.pair or len(self.shape) != 3 or len(self.head) < 352:
            return False
        (size,), (bitpix,), pixdim = self.field("i", 0), self.field("h", 72), self.field("8f", 76)
        (slope, inter), (qform, sform) = self.field("2f", 112), self.field("2h", 252)
        unscaled = slope == 0 or not math.isfinite(slope) or (slope, inter) == (1.0, 0.0)
        return (
            size == 348
            and bitpix == 8 * self.dtype.itemsize
            and pixdim[0] in (-1.0, 1.0)
            and all(p > 0 for p in pixdim[1:4])
            and self.vox_offset >= 352
            and self.vox_offset % 16 == 0
            and self.head[348] == 0  # no extensions follow the header
            and qform in XFORM_CODES
            and sform in XFORM_CODES
            and sform > 0
            and unscaled
        )

    def sform(self) -> np.ndarray:
        """The (4, 4) sform (RAS), float64, as nibabel gives it."""
        affine = np.eye(4)
        affine[:3] = np.array(self.field("12f", 280), dtype=np.float64).reshape(3, 4)
        return affine

    def description(self) -> str:
        """``descrip``, the header's free text (80 bytes)."""
        return self.head[148:228].rstrip(b"\0").decode("latin-1").strip("\0 ")


def check_header(path: Path) -> Declared:
    """Tell truncated, mislabelled and impossible headers apart before nibabel's generic errors.

    Sizes are checked against the bytes present (and a voxel cap) here, so a header that
    declares 100000^3 voxels is refused before anything is allocated or inflated.
    """
    try:
        with open_stream(path) as stream:
            header = stream.read(548)
    except (*TRUNCATION_ERRORS, OSError) as exc:
        raise truncated(path, str(exc)) from exc
    if not magic_ok(header):
        if len(header) < 348 and header[:4] in SIZEOF_HDR:
            raise truncated(path, f"the header stops after {len(header)} of 348 bytes")
        raise UnreadableVolume(
            f"{path.name}: not a NIfTI file: no 'n+1' magic at byte 344 (found "
            f"{header[344:348]!r}); check it was not renamed from another format or damaged."
        )
    declared = _declared(path, header)
    _check_size(path, declared)
    return declared


def _declared(path: Path, header: bytes) -> Declared:
    """Parse dim, datatype and vox_offset (NIfTI-1 or -2, either byte order) and check them."""
    version = 2 if header[4:8] in NIFTI2_MAGICS else 1
    if version == 2 and len(header) < 540:
        raise truncated(path, f"the NIfTI-2 header stops after {len(header)} of 540 bytes")
    size, layout = (540, NIFTI2_LAYOUT) if version == 2 else (348, NIFTI1_LAYOUT)
    endian: Literal["<", ">"] = "<" if struct.unpack("<i", header[:4])[0] == size else ">"
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
    if code not in DATATYPES:
        raise UnreadableVolume(f"{bad} datatype code {code} is not a NIfTI type; {fix}")
    name, kind = DATATYPES[code]
    if kind is None:
        raise UnreadableVolume(
            f"{path.name}: its voxels are of NIfTI type {name!r}, not one real number each "
            "(MISS draws density surfaces); convert it to a greyscale (scalar) volume first."
        )
    if not np.isfinite(vox_offset) or vox_offset < 0:
        raise UnreadableVolume(f"{bad} vox_offset {vox_offset} is not a byte offset; {fix}")
    pair = header[344:348] == b"ni1\0" or header[4:8] == b"ni2\0"
    return Declared(version, pair, shape, np.dtype(kind), vox_offset, endian, header)


def _check_size(path: Path, declared: Declared) -> None:
    """Header sizes against the voxel cap and the bytes (or compressed bytes) on disk."""
    data_path = path.with_suffix(".img") if declared.pair else path
    if not data_path.is_file():
        raise UnreadableVolume(
            f"{path.name}: a NIfTI header whose voxels live in {data_path.name}, which is not "
            "there; put the .img beside the .hdr."
        )
    on_disk = data_path.stat().st_size
    gz = gzipped(data_path)
    check_declared_size(path, declared.shape, declared.dtype.itemsize, on_disk if gz else None)
    if not gz and on_disk < declared.needed:
        raise truncated(path, f"it has {on_disk} bytes, the header needs {declared.needed}")
    if gz and declared.needed > DEFLATE_MAX_RATIO * on_disk:  # vox_offset can be absurd too
        raise truncated(
            path, f"the header needs {declared.needed} bytes; {on_disk} compressed cannot hold them"
        )
    if gz:
        what = codecs.declared_text(declared.shape, declared.dtype)
        codecs.check_decoded(path, declared.needed, on_disk, "gzip", what)


def open_stream(path: Path) -> io.BufferedIOBase:
    """The file's bytes, inflated when they are gzipped (whatever its name says)."""
    return gzip.open(path, "rb") if gzipped(path) else path.open("rb")


def gzipped(path: Path) -> bool:
    """True when the file's first bytes are gzip's magic, whatever its name."""
    with path.open("rb") as stream:
        return stream.read(2) == GZIP_MAGIC


def magic_ok(header: bytes) -> bool:
    """True when ``header`` holds NIfTI-1 or NIfTI-2 magic where each puts it."""
    return header[344:348] in NIFTI1_MAGICS or header[4:8] in NIFTI2_MAGICS


def truncated(path: Path, detail: str) -> UnreadableVolume:
    """The error for a file that ends early or is damaged, with ``detail``."""
    return UnreadableVolume(
        f"{path.name}: the file is truncated or damaged ({detail}); copy or download it again."
    )
