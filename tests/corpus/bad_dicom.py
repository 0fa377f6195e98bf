"""DICOM series that are damaged, inconsistent or incomplete (folders of small CT slices)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING

from pydicom.encaps import encapsulate
from pydicom.filebase import DicomBytesIO
from pydicom.filewriter import write_dataset
from pydicom.uid import JPEG2000Lossless, RLELossless

from corpus.files import OTHER_SERIES_UID, dicom_bytes, dicom_slice, write_series

if TYPE_CHECKING:
    from corpus.cases import Writer


def patch(data: bytes, old: bytes, new: bytes) -> bytes:
    """Replace the one occurrence of ``old`` by ``new`` of the same length (keeps offsets valid)."""
    assert data.count(old) == 1 and len(old) == len(new), (old, new)
    return data.replace(old, new)


def write(w: Writer) -> None:
    _truncated(w)
    _pixel_data(w)
    _sizes_and_series(w)
    _positions(w)
    _bad_geometry(w)
    _encodings(w)


def _truncated(w: Writer) -> None:
    whole = dicom_bytes(dicom_slice(0))
    w.file(
        "dicom-truncated-mid-header",
        ".dcm",
        whole[:200],
        "dicom",
        "error",
        "a lone file cut inside its meta header: nothing to read",
    )
    w.file(
        "dicom-truncated-mid-pixels",
        ".dcm",
        whole[:-25],
        "dicom",
        "error",
        "a lone slice (a surface needs two) whose pixel data is cut short",
    )
    series = write_series(
        w.folder(
            "dicom-series-one-cut-mid-header",
            "dicom",
            "ok",
            "the cut file has no readable header: skipped with a note, "
            "the other three slices stack (gap resampled)",
        )
    )
    series[1].write_bytes(series[1].read_bytes()[:300])
    series = write_series(
        w.folder(
            "dicom-series-one-cut-mid-pixels",
            "dicom",
            "error",
            "a slice inside the series has half its pixels: silently "
            "dropping it would hide data loss, so the file is named",
        )
    )
    series[2].write_bytes(series[2].read_bytes()[:-30])
    folder = w.folder(
        "dicom-non-utf8-names",
        "dicom",
        "ok",
        "file names in latin-1 bytes (not UTF-8) on disk: read as any other",
    )
    for k, path in enumerate(write_series(folder)):
        path.rename(folder / os.fsdecode(b"S\xe9rie-%d.dcm" % k))
    folder = w.folder(
        "dicom-non-utf8-name-damaged",
        "dicom",
        "error",
        "a damaged slice whose name is not UTF-8: the message naming it must "
        "still be valid text (JSON, logs)",
    )
    for k, path in enumerate(write_series(folder)):
        cut = path.read_bytes()[:-30] if k == 1 else path.read_bytes()
        path.unlink()
        (folder / os.fsdecode(b"S\xe9rie-%d.dcm" % k)).write_bytes(cut)
    w.file(
        "dicom-text-renamed",
        ".dcm",
        b"Patient notes, not an image.\n" * 20,
        "dicom",
        "error",
        "plain text with a .dcm name",
    )


def _slices(folder: Path, count: int = 3, edit=None, **args: object) -> None:
    """``count`` slices into ``folder``, each passed through ``edit(k, ds)`` first."""
    for k in range(count):
        ds = dicom_slice(k, **args)  # type: ignore[arg-type]
        if edit is not None:
            edit(k, ds)
        (folder / f"IM{k + 1:04d}.dcm").write_bytes(dicom_bytes(ds))


def _pixel_data(w: Writer) -> None:
    _slices(
        w.folder("dicom-no-pixeldata", "dicom", "error", "headers without PixelData"),
        edit=lambda k, ds: delattr(ds, "PixelData"),
    )
    _slices(
        w.folder(
            "dicom-pixeldata-short",
            "dicom",
            "error",
            "one slice's PixelData holds half the bytes Rows x Columns needs",
        ),
        edit=lambda k, ds: setattr(ds, "PixelData", ds.PixelData[:30]) if k == 1 else None,
    )
    _slices(
        w.folder(
            "dicom-rows-columns-exceed-data",
            "dicom",
            "error",
            "Rows/Columns 500x600 but 5x6 pixels stored",
        ),
        edit=lambda k, ds: (setattr(ds, "Rows", 500), setattr(ds, "Columns", 600)),
    )
    _slices(
        w.folder(
            "dicom-rows-columns-absurd",
            "dicom",
            "error",
            "Rows/Columns 65535x65535 with 60 bytes of pixels: refused without allocating 8 GB",
        ),
        edit=lambda k, ds: (setattr(ds, "Rows", 65535), setattr(ds, "Columns", 65535)),
    )
    _slices(
        w.folder("dicom-rows-zero", "dicom", "error", "Rows 0: an image without pixels"),
        edit=lambda k, ds: setattr(ds, "Rows", 0),
    )
    _slices(
        w.folder(
            "dicom-rgb",
            "dicom",
            "error",
            "colour (3 samples per pixel) slices cannot be a density volume",
        ),
        edit=_rgb,
    )
    _slices(
        w.folder(
            "dicom-multiframe",
            "dicom",
            "error",
            "NumberOfFrames 2 on every file: enhanced objects are not stacked",
        ),
        edit=_two_frames,
    )
    _slices(
        w.folder(
            "dicom-bits-allocated-12",
            "dicom",
            "error",
            "BitsAllocated 12 is not a valid native pixel layout",
        ),
        edit=lambda k, ds: setattr(ds, "BitsAllocated", 12),
    )


def _rgb(k: int, ds) -> None:
    ds.SamplesPerPixel, ds.PhotometricInterpretation, ds.PlanarConfiguration = 3, "RGB", 0
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 8, 8, 7, 0
    ds.PixelData = bytes(range(90))


def _two_frames(k: int, ds) -> None:
    ds.NumberOfFrames = 2
    ds.PixelData = ds.PixelData * 2


def _sizes_and_series(w: Writer) -> None:
    write_series(w.folder("dicom-series-valid", "dicom", "ok", "the reference: 4 good slices"))
    folder = w.folder(
        "dicom-sizes-differ-across-slices",
        "dicom",
        "ok",
        "one 7x9 slice among 5x6 ones: the commonest size is kept, with a note",
    )
    write_series(folder, 3)
    (folder / "IM0009.dcm").write_bytes(dicom_bytes(dicom_slice(3, rows=7, columns=9)))
    folder = w.folder(
        "dicom-mixed-series",
        "dicom",
        "ok",
        "two SeriesInstanceUIDs of different sizes: the larger series is read",
    )
    write_series(folder / "a", 4)
    write_series(folder / "b", 3, rows=9, columns=7, series_uid=OTHER_SERIES_UID)
    folder = w.folder(
        "dicom-mixed-series-same-count",
        "dicom",
        "ok",
        "two series of 3 slices each: one is read, the other listed",
    )
    write_series(folder / "a", 3)
    write_series(folder / "b", 3, rows=9, columns=7, series_uid=OTHER_SERIES_UID)
    write_series(
        w.folder("dicom-single-slice", "dicom", "error", "one slice: a surface needs at least two"),
        1,
    )
    folder = w.folder(
        "dicom-folder-with-junk",
        "dicom",
        "ok",
        "a good series beside a README and random bytes: junk skipped",
    )
    write_series(folder)
    (folder / "README.txt").write_text("exported by a CD viewer\n")
    (folder / "data.bin").write_bytes(bytes(range(256)) * 8)
    folder = w.folder(
        "dicom-no-preamble",
        "dicom",
        "ok",
        "old files without the 128-byte preamble or meta group (implicit VR)",
    )
    for k in range(3):
        ds = dicom_slice(k)
        del ds.file_meta
        stream = DicomBytesIO()
        stream.is_implicit_VR, stream.is_little_endian = True, True
        write_dataset(stream, ds)  # implicit VR little endian, starts with group 0008
        (folder / f"IM{k + 1:04d}").write_bytes(stream.getvalue())


def _positions(w: Writer) -> None:
    _slices(
        w.folder(
            "dicom-all-same-position",
            "dicom",
            "error",
            "three slices at one ImagePositionPatient: one distinct slice",
        ),
        edit=lambda k, ds: setattr(ds, "ImagePositionPatient", [0.0, 0.0, 5.0]),
    )
    folder = w.folder(
        "dicom-one-duplicate-position",
        "dicom",
        "ok",
        "a repeated slice (new SOP UID, same position) is dropped with a note",
    )
    write_series(folder)
    ds = dicom_slice(1)
    ds.SOPInstanceUID = ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID + ".99"
    (folder / "IM0099.dcm").write_bytes(dicom_bytes(ds))
    _slices(
        w.folder(
            "dicom-no-position",
            "dicom",
            "error",
            "no ImagePositionPatient/ImageOrientationPatient: cannot stack in space",
        ),
        edit=lambda k, ds: (
            delattr(ds, "ImagePositionPatient"),
            delattr(ds, "ImageOrientationPatient"),
        ),
    )
    _slices(
        w.folder(
            "dicom-one-without-position",
            "dicom",
            "ok",
            "one of four slices lacks ImagePositionPatient: skipped with a note",
        ),
        count=4,
        edit=lambda k, ds: delattr(ds, "ImagePositionPatient") if k == 3 else None,
    )


def _bad_geometry(w: Writer) -> None:
    _slices(
        w.folder(
            "dicom-parallel-orientation",
            "dicom",
            "error",
            "row and column directions parallel: no slice normal",
        ),
        edit=lambda k, ds: setattr(ds, "ImageOrientationPatient", [1, 0, 0, 1, 0, 0]),
    )
    _slices(
        w.folder(
            "dicom-short-orientation",
            "dicom",
            "error",
            "ImageOrientationPatient with 3 values instead of 6",
        ),
        edit=lambda k, ds: setattr(ds, "ImageOrientationPatient", [1, 0, 0]),
    )
    _slices(
        w.folder(
            "dicom-short-position",
            "dicom",
            "error",
            "ImagePositionPatient with 2 values instead of 3",
        ),
        edit=lambda k, ds: setattr(ds, "ImagePositionPatient", [0, float(k)]),
    )
    _patched(
        w.folder(
            "dicom-nan-position",
            "dicom",
            "error",
            "ImagePositionPatient NaN on every slice: no usable position",
        ),
        b"123.25",
        b"NaN   ",
        position=True,
    )
    _slices(
        w.folder(
            "dicom-position-outlier",
            "dicom",
            "error",
            "slices at 0, 2.5, 5 and 10 km: not one stack; a regular grid would "
            "need 4 million slices",
        ),
        count=4,
        edit=lambda k, ds: ds.ImagePositionPatient.__setitem__(2, 1e7) if k == 3 else None,
    )
    _slices(
        w.folder(
            "dicom-zero-pixel-spacing",
            "dicom",
            "ok",
            "PixelSpacing 0\\0 is unusable: 1 mm assumed, as for a missing one, with a note",
        ),
        edit=lambda k, ds: setattr(ds, "PixelSpacing", [0, 0]),
    )
    _patched(
        w.folder(
            "dicom-nan-rescale",
            "dicom",
            "error",
            "RescaleSlope NaN: the voxels have no real values",
        ),
        b"7.25",
        b"NaN ",
        slope=True,
    )
    _patched(
        w.folder("dicom-text-rescale", "dicom", "error", "RescaleSlope 'abc': not a number"),
        b"7.25",
        b"abc ",
        slope=True,
    )


def _patched(
    folder: Path, old: bytes, new: bytes, position: bool = False, slope: bool = False
) -> None:
    """Slices whose DS value ``old`` (a valid placeholder) is overwritten by invalid ``new``."""
    for k in range(3):
        ds = dicom_slice(k)
        if position:
            ds.ImagePositionPatient = [-2.0, -1.6, float(old)]
        if slope:
            ds.RescaleSlope = old.decode()
        (folder / f"IM{k + 1:04d}.dcm").write_bytes(patch(dicom_bytes(ds), old, new))


def _encodings(w: Writer) -> None:
    for name, syntax in (("jpeg2000", JPEG2000Lossless), ("rle", RLELossless)):
        _slices(
            w.folder(
                f"dicom-{name}-garbage",
                "dicom",
                "error",
                f"{name} transfer syntax whose fragments are random bytes",
            ),
            edit=lambda k, ds, syntax=syntax: _garbage_payload(k, ds, syntax),
        )


def _garbage_payload(k: int, ds, syntax) -> None:
    ds.file_meta.TransferSyntaxUID = syntax
    ds.PixelData = encapsulate([bytes((k * 37 + i * 11) % 256 for i in range(64))])
    ds["PixelData"].VR = "OB"
    ds["PixelData"].is_undefined_length = True
