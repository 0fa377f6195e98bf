"""Small valid inputs written from code: the seeds every bad case is derived from.

No patient data: DICOM slices carry made-up UIDs and names, voxels are a ramp. Each
builder returns bytes (or writes a file and returns its path) so that a case can cut,
patch or zip them before they touch the disk.
"""

from __future__ import annotations

import gzip
import io
import struct
import zipfile
import zlib
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import nibabel as nib
import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, CTImageStorage, ExplicitVRLittleEndian

#: Made-up UID root for the corpus (2.25 is the UUID-derived root anyone may use).
UID_ROOT = "2.25.1000"
STUDY_UID = f"{UID_ROOT}.1"
SERIES_UID = f"{UID_ROOT}.2"
OTHER_SERIES_UID = f"{UID_ROOT}.3"
#: Voxels of every seed volume: (X, Y, Z) = (6, 5, 4), values -1000..1300 (CT-like).
SHAPE = (6, 5, 4)


def ramp(shape: tuple[int, ...] = SHAPE, dtype: str = "int16") -> np.ndarray:
    """A deterministic (X, Y, Z) volume whose voxels all differ: -1000 and up in steps of 20."""
    return (np.arange(int(np.prod(shape))).reshape(shape, order="F") * 20 - 1000).astype(dtype)


# ---------------------------------------------------------------- DICOM


def dicom_slice(
    k: int = 0,
    rows: int = 5,
    columns: int = 6,
    series_uid: str = SERIES_UID,
    spacing: float = 2.5,
) -> Dataset:
    """Slice ``k`` of an axial CT series: int16 pixels, rescale -1024, 0.8 mm pixels."""
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = CTImageStorage
    meta.MediaStorageSOPInstanceUID = f"{series_uid}.{k + 1}"
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = CTImageStorage
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.StudyInstanceUID = STUDY_UID
    ds.SeriesInstanceUID = series_uid
    ds.FrameOfReferenceUID = f"{UID_ROOT}.4"
    ds.Modality = "CT"
    ds.PatientName = "Corpus^Synthetic"
    ds.PatientID = "CORPUS-0"
    ds.SeriesDescription = "MISS corpus"
    ds.InstanceNumber = k + 1
    ds.ImagePositionPatient = [-2.0, -1.6, k * spacing]
    ds.ImageOrientationPatient = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    ds.PixelSpacing = [0.8, 0.8]
    ds.SliceThickness = spacing
    ds.RescaleSlope = 1
    ds.RescaleIntercept = -1024
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.Rows, ds.Columns = rows, columns
    ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
    pixels = (np.arange(rows * columns, dtype=np.int16).reshape(rows, columns) * 10) + 100 * k
    ds.PixelData = pixels.astype("<i2").tobytes()
    return ds


def dicom_bytes(ds: Dataset) -> bytes:
    """The Part 10 file (preamble, ``DICM``, meta group, data set) as bytes."""
    stream = io.BytesIO()
    pydicom.dcmwrite(stream, ds, enforce_file_format=True)
    return stream.getvalue()


def write_series(folder: Path, count: int = 4, **slice_args: object) -> list[Path]:
    """``count`` slices 2.5 mm apart as ``IM0001.dcm`` ...; returns their paths."""
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k in range(count):
        path = folder / f"IM{k + 1:04d}.dcm"
        path.write_bytes(dicom_bytes(dicom_slice(k, **slice_args)))  # type: ignore[arg-type]
        paths.append(path)
    return paths


# ---------------------------------------------------------------- NIfTI, NRRD, MetaImage


def nifti_bytes(
    data: np.ndarray | None = None, gz: bool = False, affine: np.ndarray | None = None
) -> bytes:
    """A NIfTI-1 single file (``n+1``), sform and qform set; gzip-compressed when ``gz``."""
    data = ramp() if data is None else data
    aff = np.diag([0.8, 0.8, 2.5, 1.0]) if affine is None else affine
    img = nib.Nifti1Image(data, aff)
    img.header.set_xyzt_units("mm")
    raw = img.to_bytes()
    return gzip.compress(raw, mtime=0) if gz else raw


def nrrd_bytes(data: np.ndarray | None = None, encoding: str = "raw", extra: str = "") -> bytes:
    """An attached NRRD (int16, little endian, LPS space directions) with ``extra`` header lines."""
    data = ramp() if data is None else data
    payload = np.asfortranarray(data).astype("<i2").tobytes(order="F")
    if encoding == "gzip":
        payload = gzip.compress(payload, mtime=0)
    sizes = " ".join(map(str, data.shape))
    header = (
        f"NRRD0004\ntype: short\ndimension: {data.ndim}\nsizes: {sizes}\nendian: little\n"
        f"encoding: {encoding}\nspace: left-posterior-superior\n"
        "space directions: (0.8,0,0) (0,0.8,0) (0,0,2.5)\nspace origin: (-2,-1.6,0)\n"
    )
    return (header + extra + "\n").encode() + payload


def mha_header(sizes: Iterable[int], data_file: str = "LOCAL", extra: str = "") -> str:
    """MetaImage header lines for int16 voxels (ElementDataFile last, as the format wants)."""
    dims = list(sizes)
    return (
        "ObjectType = Image\n"
        f"NDims = {len(dims)}\n"
        "BinaryData = True\nBinaryDataByteOrderMSB = False\nCompressedData = False\n"
        "TransformMatrix = 1 0 0 0 1 0 0 0 1\nOffset = -2 -1.6 0\n"
        "ElementSpacing = 0.8 0.8 2.5\n"
        f"DimSize = {' '.join(map(str, dims))}\nElementType = MET_SHORT\n{extra}"
        f"ElementDataFile = {data_file}\n"
    )


def mha_bytes(data: np.ndarray | None = None, extra: str = "") -> bytes:
    """A ``.mha`` (header and voxels in one file)."""
    data = ramp() if data is None else data
    voxels = np.asfortranarray(data).astype("<i2").tobytes(order="F")
    return mha_header(data.shape, extra=extra).encode() + voxels


# ---------------------------------------------------------------- zip archives


def zip_bytes(members: dict[str, bytes], method: int = zipfile.ZIP_DEFLATED) -> bytes:
    """An ordinary zip of ``{name: content}``."""
    stream = io.BytesIO()
    with zipfile.ZipFile(stream, "w", method) as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    return stream.getvalue()


@dataclass(frozen=True)
class RawMember:
    """A zip member laid out by hand, so that it can lie (names, sizes, links).

    ``size`` and ``crc`` are what the headers declare; ``data`` is what is stored
    (deflated when ``method`` is 8).
    """

    name: bytes
    data: bytes
    size: int
    crc: int
    method: int = zipfile.ZIP_DEFLATED
    flags: int = 0
    unix_mode: int = 0o100644


def raw_member(name: bytes, content: bytes, **overrides: object) -> RawMember:
    """A truthful deflated member; ``overrides`` then make it lie."""
    deflater = zlib.compressobj(6, zlib.DEFLATED, -15)
    data = deflater.compress(content) + deflater.flush()
    fields = {"size": len(content), "crc": zlib.crc32(content)} | overrides
    return RawMember(name=name, data=data, **fields)  # type: ignore[arg-type]


def raw_zip(members: list[RawMember]) -> bytes:
    """Local headers, data, central directory and end record, little-endian (APPNOTE 4.3)."""
    out, central = io.BytesIO(), io.BytesIO()
    for m in members:
        offset = out.tell()
        out.write(
            struct.pack(
                "<4s5H3L2H",
                b"PK\x03\x04",
                20,
                m.flags,
                m.method,
                0,
                0x21,
                m.crc,
                len(m.data),
                m.size,
                len(m.name),
                0,
            )
        )
        out.write(m.name + m.data)
        central.write(
            struct.pack(
                "<4s6H3L5H2L",
                b"PK\x01\x02",
                0x0314,
                20,
                m.flags,
                m.method,
                0,
                0x21,
                m.crc,
                len(m.data),
                m.size,
                len(m.name),
                0,
                0,
                0,
                0,
                m.unix_mode << 16,
                offset,
            )
        )
        central.write(m.name)
    directory = central.getvalue()
    end = struct.pack(
        "<4s4H2LH", b"PK\x05\x06", 0, 0, len(members), len(members), len(directory), out.tell(), 0
    )
    return out.getvalue() + directory + end


def deflate_with_zeros(prefix: bytes, zeros: int) -> tuple[bytes, int]:
    """Raw deflate of ``prefix`` + ``zeros`` zero bytes, and the CRC-32 of that whole.

    The zeros cost ~1 KB per MiB without being compressed one by one: one MiB of zeros
    is deflated once after a full flush (which byte-aligns the output and forgets the
    history), and that block is repeated. ``zeros`` must be a multiple of 1 MiB.
    """
    chunk = 1 << 20
    if zeros % chunk:
        raise ValueError("zeros must be a multiple of 1 MiB")
    deflater = zlib.compressobj(9, zlib.DEFLATED, -15)
    head = deflater.compress(prefix) + deflater.flush(zlib.Z_FULL_FLUSH)
    block = deflater.compress(bytes(chunk)) + deflater.flush(zlib.Z_FULL_FLUSH)
    tail = deflater.flush()
    crc, empty = zlib.crc32(prefix), bytes(chunk)
    for _ in range(zeros // chunk):
        crc = zlib.crc32(empty, crc)
    return head + block * (zeros // chunk) + tail, crc


def zeros_member(name: bytes, size: int) -> RawMember:
    """A member of ``size`` zero bytes deflated ~1000:1 (a zip bomb's payload)."""
    data, crc = deflate_with_zeros(b"", size)
    return RawMember(name=name, data=data, size=size, crc=crc)


def gzip_with_zeros(prefix: bytes, zeros: int) -> bytes:
    """A gzip member (RFC 1952) holding ``prefix`` then ``zeros`` zero bytes."""
    data, crc = deflate_with_zeros(prefix, zeros)
    size = (len(prefix) + zeros) & 0xFFFFFFFF
    return b"\x1f\x8b\x08\x00\x00\x00\x00\x00\x00\x03" + data + struct.pack("<2L", crc, size)
