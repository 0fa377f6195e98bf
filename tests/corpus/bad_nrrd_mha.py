"""NRRD and MetaImage headers that lie about sizes, name missing or foreign data files,
or use encodings MISS cannot read."""

from __future__ import annotations

import bz2
import gzip
import zlib
from typing import TYPE_CHECKING

import numpy as np

from corpus.files import gzip_with_zeros, mha_bytes, mha_header, nrrd_bytes, ramp

if TYPE_CHECKING:
    from corpus.cases import Expect, Writer

VOXELS = np.asfortranarray(ramp()).astype("<i2").tobytes(order="F")


def nrrd_text(
    sizes: str = "6 5 4", dimension: int = 3, extra: str = "", encoding: str = "raw"
) -> str:
    """An NRRD header (no blank line: the caller adds it or a ``data file`` line)."""
    return (
        f"NRRD0004\ntype: short\ndimension: {dimension}\nsizes: {sizes}\nendian: little\n"
        f"encoding: {encoding}\nspacings: 0.8 0.8 2.5\n{extra}"
    )


def write(w: Writer) -> None:
    _nrrd(w)
    _nrrd_files(w)
    _mha(w)
    _mhd(w)


def _nrrd(w: Writer) -> None:
    def add(name: str, content: bytes, expect: Expect, why: str) -> None:
        w.file(name, ".nrrd", content, "nrrd", expect, why)

    add("nrrd-valid", nrrd_bytes(), "ok", "the reference")
    add("nrrd-valid-gzip", nrrd_bytes(encoding="gzip"), "ok", "the reference, gzip encoded")
    for name, sizes, why in (
        ("negative", "6 -5 4", "a negative size"),
        ("not-numbers", "6 five 4", "a size that is not a number"),
        ("count-mismatch", "6 5", "2 sizes for dimension 3"),
        ("absurd", "100000 100000 100000", "10^15 voxels declared before 240 bytes of data"),
        ("overflow", "4294967296 4294967296 4294967296", "a voxel count that overflows int64"),
    ):
        add(f"nrrd-sizes-{name}", (nrrd_text(sizes) + "\n").encode() + VOXELS, "error", why)
    add(
        "nrrd-sizes-absurd-gzip",
        (nrrd_text("100000 100000 100000", encoding="gzip") + "\n").encode()
        + gzip.compress(VOXELS),
        "error",
        "10^15 voxels declared in a 300-byte gzip stream",
    )
    add(
        "nrrd-encoding-unknown",
        (nrrd_text(encoding="zstd") + "\n").encode() + VOXELS,
        "error",
        "encoding zstd is not one NRRD defines",
    )
    add(
        "nrrd-type-unknown",
        (nrrd_text().replace("short", "block") + "\n").encode() + VOXELS,
        "error",
        "type block has no numeric meaning",
    )
    add(
        "nrrd-header-only",
        nrrd_text().encode(),
        "error",
        "no blank line and no data file: no voxels anywhere",
    )
    add("nrrd-no-data", (nrrd_text() + "\n").encode(), "error", "a blank line, then nothing")
    add("nrrd-wrong-magic", b"NRRD0009\n" + nrrd_bytes()[9:], "error", "an unknown NRRD version")
    add(
        "nrrd-line-skip-beyond",
        (nrrd_text(extra="line skip: 1000\n") + "\n").encode() + VOXELS,
        "error",
        "line skip 1000 in data with fewer line breaks",
    )
    add(
        "nrrd-byte-skip-text",
        (nrrd_text(extra="byte skip: abc\n") + "\n").encode() + VOXELS,
        "error",
        "byte skip 'abc' is not a number",
    )
    _nrrd_fields(w)


def _nrrd_fields(w: Writer) -> None:
    def add(name: str, content: bytes, expect: Expect, why: str) -> None:
        w.file(name, ".nrrd", content, "nrrd", expect, why)

    add(
        "nrrd-space-directions-2d",
        nrrd_bytes(extra="").replace(b"(0.8,0,0) (0,0.8,0) (0,0,2.5)", b"(0.8,0) (0,0.8) (0,0)"),
        "error",
        "2-D direction vectors for 3-D space",
    )
    add(
        "nrrd-space-directions-nan",
        nrrd_bytes().replace(b"(0.8,0,0)", b"(nan,0,0)"),
        "error",
        "a NaN direction: no position for the voxels",
    )
    add(
        "nrrd-space-directions-zero",
        nrrd_bytes().replace(b"(0.8,0,0)", b"(0,0,0)  "),
        "error",
        "a zero direction: the grid has no extent",
    )
    add(
        "nrrd-ascii-garbage",
        (nrrd_text(encoding="ascii") + "\n").encode() + b"1 2 x y\n" * 40,
        "error",
        "ASCII data with words in it",
    )
    floats = " ".join(["nan", "inf", "-inf"] + ["1.5", "2.5"] * 58 + ["1.5"]).encode()
    add(
        "nrrd-ascii-nan",
        (nrrd_text(encoding="ascii").replace("short", "float") + "\n").encode() + floats,
        "ok",
        "float NaN/Inf voxels are replaced by finite extremes, with a note",
    )
    add(
        "nrrd-bzip2-damaged",
        (nrrd_text(encoding="bzip2") + "\n").encode() + bz2.compress(VOXELS)[:-20],
        "error",
        "a bzip2 stream cut short",
    )
    add(
        "nrrd-gzip-trailing-bomb",
        (nrrd_text(encoding="gzip") + "\n").encode() + gzip_with_zeros(VOXELS, 1 << 30),
        "ok",
        "the 240 bytes of voxels followed by 1 GiB of zeros in the gzip stream: only "
        "the voxels the header declares are inflated",
    )


def _nrrd_files(w: Writer) -> None:
    folder = w.folder(
        "nrrd-detached-valid", "nrrd", "ok", "the reference, .nhdr + .raw", inside="volume.nhdr"
    )
    (folder / "volume.nhdr").write_text(nrrd_text(extra="data file: volume.raw\n"))
    (folder / "volume.raw").write_bytes(VOXELS)
    for name, spec, why in (
        ("missing-data-file", "volume.raw", "the detached data file is not there"),
        (
            "data-file-absolute",
            str(w.dest.resolve() / "secret.raw"),
            "an absolute data file: could read any file on a server as voxels",
        ),
        ("data-file-parent", "../secret.raw", "a data file outside the header's folder"),
        ("data-file-huge-range", "s.%03d 1 1000000000 1", "a billion detached slice files"),
        ("data-file-list-empty", "LIST", "LIST with no names after it"),
    ):
        folder = w.folder(f"nrrd-{name}", "nrrd", "error", why, inside="volume.nhdr")
        (folder / "volume.nhdr").write_text(nrrd_text(extra=f"data file: {spec}\n"))
    (w.dest / "secret.raw").write_bytes(VOXELS)  # what data-file-parent points at


def _mha(w: Writer) -> None:
    def add(name: str, content: bytes, expect: Expect, why: str) -> None:
        w.file(name, ".mha", content, "mha", expect, why)

    add("mha-valid", mha_bytes(), "ok", "the reference")
    text = mha_header((6, 5, 4)).replace("ElementDataFile = LOCAL\n", "")
    add("mha-no-element-data-file", text.encode() + VOXELS, "error", "no ElementDataFile line")
    add(
        "mha-dimsize-too-large",
        mha_header((6, 5, 40)).encode() + VOXELS,
        "error",
        "DimSize 6 5 40 but data for 6 5 4",
    )
    add(
        "mha-dimsize-smaller",
        mha_header((6, 5, 2)).encode() + VOXELS,
        "ok",
        "DimSize 6 5 2 with data for 4 slices: the declared voxels are read",
    )
    add(
        "mha-dimsize-absurd",
        mha_header((100000,) * 3).encode() + VOXELS,
        "error",
        "10^15 voxels declared beside 240 bytes",
    )
    add(
        "mha-dimsize-count-mismatch",
        mha_header((6, 5, 4))
        .replace("NDims = 3", "NDims = 4")
        .replace("DimSize = 6 5 4", "DimSize = 6 5")
        .encode()
        + VOXELS,
        "error",
        "NDims 4 but two sizes",
    )
    add(
        "mha-dimsize-negative", mha_header((6, -5, 4)).encode() + VOXELS, "error", "a negative size"
    )
    add(
        "mha-ndims-huge",
        mha_header((6, 5, 4)).replace("NDims = 3", "NDims = 100000").encode() + VOXELS,
        "error",
        "NDims 100000: a default 100000^2 direction matrix must not be built",
    )
    add(
        "mha-element-type-unknown",
        mha_bytes().replace(b"MET_SHORT", b"MET_WEIRD"),
        "error",
        "an ElementType MetaIO does not define",
    )
    add("mha-ndims-2", mha_header((6, 20)).encode() + VOXELS, "error", "a 2-D image")
    add(
        "mha-channels-zero",
        mha_bytes(extra="ElementNumberOfChannels = 0\n"),
        "error",
        "zero channels per voxel",
    )
    add(
        "mha-spacing-zero",
        mha_bytes().replace(b"ElementSpacing = 0.8 0.8 2.5", b"ElementSpacing = 0 0 0      "),
        "error",
        "voxel spacing 0: the grid has no extent",
    )
    header = mha_header((6, 5, 4), extra="CompressedDataSize = 50\n").replace(
        "CompressedData = False", "CompressedData = True"
    )
    add(
        "mha-compressed-damaged",
        header.encode() + zlib.compress(VOXELS)[:50],
        "error",
        "a zlib stream cut short",
    )
    header = mha_header((100000,) * 3).replace("CompressedData = False", "CompressedData = True")
    add(
        "mha-compressed-absurd",
        header.encode() + zlib.compress(VOXELS),
        "error",
        "10^15 voxels declared in a 300-byte zlib stream",
    )
    add("mha-header-only", mha_header((6, 5, 4)).encode(), "error", "LOCAL data, but none follows")


def _mhd(w: Writer) -> None:
    folder = w.folder("mhd-valid", "mha", "ok", "the reference, .mhd + .raw", inside="volume.mhd")
    (folder / "volume.mhd").write_text(mha_header((6, 5, 4), "volume.raw"))
    (folder / "volume.raw").write_bytes(VOXELS)
    for name, spec, why in (
        ("missing-raw", "volume.raw", "the data file is not there"),
        (
            "data-file-absolute",
            str(w.dest.resolve() / "secret.raw"),
            "an absolute data file: could read any file on a server as voxels",
        ),
        ("data-file-parent", "../secret.raw", "a data file outside the header's folder"),
    ):
        folder = w.folder(f"mhd-{name}", "mha", "error", why, inside="volume.mhd")
        (folder / "volume.mhd").write_text(mha_header((6, 5, 4), spec))
