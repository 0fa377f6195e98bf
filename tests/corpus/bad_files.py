"""Files that are not what their name says: empty, random bytes, text, renamed images."""

from __future__ import annotations

import io
from typing import TYPE_CHECKING

import numpy as np
from PIL import Image

if TYPE_CHECKING:
    from corpus.cases import Kind, Writer

#: Every extension MISS (or SimpleITK behind it) might claim, and none at all.
EXTENSIONS: dict[str, Kind] = {
    ".dcm": "dicom",
    ".dicom": "dicom",
    ".ima": "dicom",
    ".zip": "zip",
    ".nii": "nifti",
    ".nii.gz": "nifti",
    ".nrrd": "nrrd",
    ".nhdr": "nrrd",
    ".mha": "mha",
    ".mhd": "mha",
    ".raw": "other",
    ".hdr": "other",
    ".img": "other",
    ".vtk": "other",
    ".png": "other",
    ".tif": "other",
    ".txt": "other",
    "": "other",
}


def slug(suffix: str) -> str:
    return suffix.strip(".").replace(".", "-") or "no-extension"


def png_bytes(shape: tuple[int, int] = (5, 6)) -> bytes:
    stream = io.BytesIO()
    Image.fromarray(np.arange(shape[0] * shape[1], dtype=np.uint8).reshape(shape)).save(
        stream, "PNG"
    )
    return stream.getvalue()


def write(w: Writer) -> None:
    rng = np.random.default_rng(1998)
    for suffix, kind in EXTENSIONS.items():
        w.file(f"empty-{slug(suffix)}", suffix, b"", kind, "error", "0 bytes")
        w.file(
            f"random-{slug(suffix)}",
            suffix,
            rng.bytes(4096),
            kind,
            "error",
            "4 KiB of random bytes",
        )
    w.file("text-renamed-nii", ".nii", b"hello\n" * 100, "nifti", "error", "text named .nii")
    w.file("png-renamed-nii", ".nii", png_bytes(), "nifti", "error", "a PNG named .nii")
    w.file("png-renamed-nrrd", ".nrrd", png_bytes(), "nrrd", "error", "a PNG named .nrrd")
    w.file("png-2d", ".png", png_bytes(), "other", "error", "a real 2-D picture: not a volume")
    w.file(
        "html-error-page",
        ".nii.gz",
        b"<html><body>502 Bad Gateway</body></html>",
        "nifti",
        "error",
        "what a failed download saves under the volume's name",
    )
    w.folder("empty-folder", "dicom", "error", "a folder with no files")
    folder = w.folder("folder-without-images", "dicom", "error", "text files only")
    (folder / "notes.txt").write_text("nothing here\n")
    (folder / ".hidden.dcm").write_bytes(b"\0" * 300)
    vtk = (
        b"# vtk DataFile Version 3.0\ncorpus\nBINARY\nDATASET STRUCTURED_POINTS\n"
        b"DIMENSIONS 100000 100000 100000\nSPACING 1 1 1\nORIGIN 0 0 0\n"
        b"POINT_DATA 1000000000000000\nSCALARS v short 1\nLOOKUP_TABLE default\n"
    )
    w.file(
        "vtk-absurd-dims",
        ".vtk",
        vtk + bytes(240),
        "other",
        "error",
        "a legacy VTK header declaring 10^15 voxels: refused before SimpleITK allocates",
    )
    w.file(
        "vtk-text-garbage",
        ".vtk",
        b"# vtk DataFile Version 3.0\n\x00\xff garbage\n",
        "other",
        "error",
        "a VTK signature followed by garbage",
    )
