"""NIfTI files with damaged headers, impossible sizes, odd voxel types and broken gzip.

Header fields are patched in place at their NIfTI-1 byte offsets (little endian):
dim 40 (8 int16), datatype 70, bitpix 72, pixdim 76 (8 float32), vox_offset 108,
qform_code 252, sform_code 254, srow_x 280 (4 float32).
"""

from __future__ import annotations

import gzip
import struct
from typing import TYPE_CHECKING

import nibabel as nib
import numpy as np

from corpus.files import SHAPE, nifti_bytes, ramp

if TYPE_CHECKING:
    from corpus.cases import Writer


def patched(raw: bytes, *edits: tuple[str, int, tuple[float, ...]]) -> bytes:
    """``raw`` with each (struct format, offset, values) written over it."""
    out = bytearray(raw)
    for fmt, offset, values in edits:
        struct.pack_into("<" + fmt, out, offset, *values)
    return bytes(out)


def dims(*values: int) -> tuple[str, int, tuple[int, ...]]:
    """A dim[] edit: dim[0] (the count) then the sizes, padded with ones."""
    return ("8h", 40, (*values, *[1] * (8 - len(values))))


def write(w: Writer) -> None:
    _valid_and_values(w)
    _sizes(w)
    _fields(w)
    _gzip(w)


def _valid_and_values(w: Writer) -> None:
    w.file("nifti-valid", ".nii", nifti_bytes(), "nifti", "ok", "the reference")
    w.file(
        "nifti-valid-gz", ".nii.gz", nifti_bytes(gz=True), "nifti", "ok", "the reference, gzipped"
    )
    data = ramp(dtype="float32")
    data[0, 0, 0], data[1, 0, 0], data[2, 0, 0] = np.nan, np.inf, -np.inf
    w.file(
        "nifti-nan-inf",
        ".nii",
        nifti_bytes(data),
        "nifti",
        "ok",
        "NaN and +/-Inf voxels are replaced by finite extremes, with a note",
    )
    w.file(
        "nifti-all-nan",
        ".nii",
        nifti_bytes(np.full(SHAPE, np.nan, np.float32)),
        "nifti",
        "error",
        "every voxel NaN: nothing to draw",
    )
    four = np.stack([ramp(), ramp() + 1], axis=3)
    w.file("nifti-4d", ".nii", nifti_bytes(four), "nifti", "ok", "4-D: the first volume is read")
    w.file(
        "nifti-5d",
        ".nii.gz",
        nifti_bytes(four[..., None], gz=True),
        "nifti",
        "ok",
        "5-D (one time point, vector dim 2): the first volume is read",
    )
    w.file("nifti-2d", ".nii", nifti_bytes(ramp((6, 5))), "nifti", "error", "a 2-D image")
    w.file(
        "nifti-one-slice",
        ".nii",
        nifti_bytes(ramp((6, 5, 1))),
        "nifti",
        "error",
        "a 6x5x1 volume: a surface needs 2 slices",
    )
    w.file(
        "nifti-complex",
        ".nii",
        nifti_bytes(ramp(dtype="complex64")),
        "nifti",
        "error",
        "complex voxels have no single density",
    )
    rgb = np.zeros(SHAPE, dtype=[("R", "u1"), ("G", "u1"), ("B", "u1")])
    w.file("nifti-rgb", ".nii", nifti_bytes(rgb), "nifti", "error", "RGB voxels are not a density")


def _sizes(w: Writer) -> None:
    raw = nifti_bytes()
    huge = patched(raw, dims(3, 30000, 30000, 30000))
    w.file(
        "nifti-absurd-dims",
        ".nii",
        huge,
        "nifti",
        "error",
        "30000^3 voxels (54 TB) declared in a 500-byte file: refused from the header",
    )
    w.file(
        "nifti-absurd-dims-gz",
        ".nii.gz",
        gzip.compress(huge, mtime=0),
        "nifti",
        "error",
        "the same header gzipped: refused before inflating or allocating",
    )
    big2 = bytearray(nib.Nifti2Image(ramp(), np.eye(4)).to_bytes())
    struct.pack_into("<8q", big2, 16, 3, 10**6, 10**6, 10**6, 1, 1, 1, 1)
    w.file(
        "nifti2-absurd-dims",
        ".nii",
        bytes(big2),
        "nifti",
        "error",
        "NIfTI-2 with 10^18 voxels declared",
    )
    w.file(
        "nifti-negative-dim",
        ".nii",
        patched(raw, dims(3, 6, -5, 4)),
        "nifti",
        "error",
        "a negative size",
    )
    w.file(
        "nifti-zero-dim",
        ".nii",
        patched(raw, dims(3, 6, 0, 4)),
        "nifti",
        "error",
        "a zero size: no voxels",
    )
    for name, value in (("zero", 0), ("nine", 9), ("negative", -2)):
        w.file(
            f"nifti-dim0-{name}",
            ".nii",
            patched(raw, ("h", 40, (value,))),
            "nifti",
            "error",
            f"dim[0] = {value}: not a dimension count 1..7",
        )
    w.file("nifti-header-only", ".nii", raw[:348], "nifti", "error", "header without voxels")
    w.file(
        "nifti-vox-offset-beyond",
        ".nii",
        patched(raw, ("f", 108, (1e6,))),
        "nifti",
        "error",
        "vox_offset points 1 MB past the end of the file",
    )
    w.file(
        "nifti-vox-offset-nan",
        ".nii",
        patched(raw, ("f", 108, (float("nan"),))),
        "nifti",
        "error",
        "vox_offset NaN",
    )


def _fields(w: Writer) -> None:
    raw = nifti_bytes()
    w.file(
        "nifti-datatype-unknown",
        ".nii",
        patched(raw, ("h", 70, (9999,))),
        "nifti",
        "error",
        "datatype code 9999 is not in the standard",
    )
    w.file(
        "nifti-bitpix-wrong",
        ".nii",
        patched(raw, ("h", 72, (64,))),
        "nifti",
        "ok",
        "bitpix 64 disagrees with datatype int16: the datatype decides, as nibabel does",
    )
    no_forms = ("2h", 252, (0, 0))
    w.file(
        "nifti-zero-pixdim",
        ".nii",
        patched(raw, no_forms, ("3f", 80, (0.0, 0.0, 0.0))),
        "nifti",
        "ok",
        "no sform/qform and voxel sizes 0: nibabel takes 1 mm and says so "
        "(a note), as MISS does for DICOM without PixelSpacing",
    )
    w.file(
        "nifti-zero-sform",
        ".nii",
        patched(raw, ("4f", 280, (0.0, 0.0, 0.0, 5.0))),
        "nifti",
        "error",
        "an sform whose first row is zero: the grid is flat",
    )
    w.file(
        "nifti-negative-pixdim",
        ".nii",
        patched(raw, ("2h", 252, (1, 0)), ("3f", 80, (-0.8, 0.8, 2.5))),
        "nifti",
        "ok",
        "qform with pixdim[1] < 0: sizes taken as magnitudes (nibabel)",
    )
    w.file(
        "nifti-nan-sform",
        ".nii",
        patched(raw, ("4f", 280, (float("nan"), 0, 0, 0))),
        "nifti",
        "error",
        "an sform with NaN: no position for the voxels",
    )
    w.file(
        "nifti-nan-scl-slope",
        ".nii",
        patched(raw, ("2f", 112, (float("nan"), 0.0))),
        "nifti",
        "ok",
        "scl_slope NaN means no scaling (NIfTI-1 standard)",
    )
    w.file(
        "nifti-bad-magic",
        ".nii",
        patched(raw, ("4s", 344, (b"xyz\0",))),
        "nifti",
        "error",
        "the magic at byte 344 is not n+1",
    )


def _gzip(w: Writer) -> None:
    gz = nifti_bytes(gz=True)
    w.file(
        "nifti-gz-ends-early",
        ".nii.gz",
        gz[: len(gz) * 2 // 3],
        "nifti",
        "error",
        "a gzip stream cut before the end of the voxels",
    )
    w.file(
        "nifti-gz-header-cut",
        ".nii.gz",
        gz[:40],
        "nifti",
        "error",
        "a gzip stream cut inside the NIfTI header",
    )
    w.file(
        "nifti-gz-bad-magic",
        ".nii.gz",
        b"\x1f\x8c" + gz[2:],
        "nifti",
        "error",
        "gzip magic damaged: neither gzip nor NIfTI",
    )
    w.file(
        "nifti-gz-not-compressed",
        ".nii.gz",
        nifti_bytes(),
        "nifti",
        "ok",
        "an uncompressed NIfTI named .nii.gz: the content decides",
    )
    w.file(
        "nifti-gzipped-named-nii",
        ".nii",
        gz,
        "nifti",
        "ok",
        "a gzipped NIfTI named .nii: the content decides",
    )
