"""NIfTI-1/2 reader (``.nii``, ``.nii.gz``): MISS's own for the plain case, else nibabel.

The header is read and checked first (:mod:`miss.io.nifti_header`). A plain single-file
volume (NIfTI-1, 3-D, an sform, no scaling, nothing nibabel would warn about: what
scanners' converters and nibabel itself write) is read by MISS directly, the same voxels
and affine nibabel gives, without loading nibabel (0.3 s, as it loads pydicom too).
Everything else goes through nibabel: its ``img.affine`` (sform, else qform, else voxel
sizes) maps to RAS; MISS works in LPS, so its first two rows are negated. Scaling
(scl_slope/scl_inter) is applied only when it is not the identity, so label maps and
raw CTs keep their integer dtype.
"""

from __future__ import annotations

import io
import logging
import math
from collections.abc import Iterator
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np

from miss.errors import UnreadableVolume
from miss.io.common import (
    RAS_TO_LPS,
    NotStreamable,
    Streamed,
    checked_affine,
    describe,
    finite_values,
    integer_dtype,
    make_volume,
    no_series,
    recorded_warnings,
    streamed_meta,
)
from miss.io.nifti_header import (
    TRUNCATION_ERRORS,
    Declared,
    check_header,
    gzipped,
    magic_ok,
    open_stream,
    truncated,
)
from miss.types import Volume

if TYPE_CHECKING:
    import nibabel as nib

#: What a volume read as CT gains in its metadata.
_CT_META: dict[str, Any] = {"modality": "CT", "units": "HU"}


def sniff(path: Path, head: bytes) -> bool:
    """``.nii``/``.nii.gz`` names, or NIfTI magic in an uncompressed header."""
    name = path.name.lower()
    return name.endswith((".nii", ".nii.gz")) or magic_ok(head)


def read(path: Path, series: str | None) -> Volume:
    """Read a NIfTI volume; see the module docstring for scaling and orientation."""
    no_series(path, series, "NIfTI")
    declared = check_header(path)
    if declared.plain:
        notes: list[str] = []
        data, affine = finite_values(path, _plain_voxels(path, declared), notes), declared.sform()
        (slope, inter), description = (1.0, 0.0), declared.description()
    else:
        data, affine, notes, (slope, inter), description = _through_nibabel(path, declared)
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
        **(_CT_META if ct else {}),
    )


def stream(path: Path) -> Streamed | None:
    """The volume as (X, Y) planes, z in order, read (and inflated) as they are asked
    for: a plain NIfTI-1 file (see the module docstring); None for any other, which
    :func:`read` reads whole. The planes raise ``NotStreamable`` at a non-finite value."""
    if not path.is_file() or not sniff(path, b""):
        return None
    declared = check_header(path)
    if not declared.plain or min(declared.shape) < 2:
        return None
    with np.errstate(all="ignore"):
        affine = checked_affine(path, RAS_TO_LPS @ declared.sform(), "nifti")
    x, y, z = (int(n) for n in declared.shape)  # plain: three
    dims = (x, y, z)
    return Streamed(
        dims,
        declared.dtype,
        affine,
        _plain_planes(path, declared),
        partial(_streamed_meta, declared.description(), dims),
        "nifti",
    )


def _streamed_meta(
    description: str, dims: tuple[int, int, int], lo: float, hi: float
) -> dict[str, Any]:
    """What :func:`read` gives as ``meta`` of a plain file whose values span lo..hi."""
    ct = _ct_reason(lo, hi, description)
    notes = ["values read as CT Hounsfield units (" + ct + ")"] if ct else []
    meta = streamed_meta(
        "nifti",
        notes,
        series_description=description,
        **(_CT_META if ct else {}),
    )
    meta["series"] = [describe(meta, dims)]
    return meta


def _plain_planes(path: Path, declared: Declared) -> Iterator[np.ndarray]:
    """The (X, Y) planes of a plain file, z in order, native byte order; one plane's
    bytes in memory at a time (gzip inflates as it goes)."""
    x, y, z = declared.shape
    stored = declared.dtype.newbyteorder(declared.endian)
    size = x * y * stored.itemsize
    try:
        with open_stream(path) as stream:
            stream.seek(int(declared.vox_offset))
            for k in range(z):
                buffer = bytearray(size)
                view, got = memoryview(buffer), 0
                while got < size and (n := stream.readinto(view[got:])):
                    got += n
                if got < size:
                    raise truncated(path, f"slice {k + 1} of {z} has {got} of {size} bytes")
                plane = np.frombuffer(buffer, dtype=stored).reshape((x, y), order="F")
                if plane.dtype.kind == "f" and not np.isfinite(plane).all():
                    raise NotStreamable(f"{path.name}: slice {k + 1} holds NaN or infinity")
                yield plane.astype(declared.dtype, copy=False)
    except (*TRUNCATION_ERRORS, OSError) as exc:
        raise truncated(path, _first_line(exc)) from exc


def _plain_voxels(path: Path, declared: Declared) -> np.ndarray:
    """The voxels of a plain file, (X, Y, Z) in its stored type and byte order, read once
    into the array (as nibabel's reader does)."""
    count = math.prod(declared.shape) * declared.dtype.itemsize
    buffer = bytearray(count)
    view, got = memoryview(buffer), 0
    try:
        with open_stream(path) as stream:
            stream.seek(int(declared.vox_offset))
            while got < count and (n := stream.readinto(view[got:])):
                got += n
    except (*TRUNCATION_ERRORS, OSError) as exc:
        raise truncated(path, _first_line(exc)) from exc
    if got < count:
        raise truncated(path, f"Expected {count} bytes of voxels, got {got}")
    dtype = declared.dtype.newbyteorder(declared.endian)
    return np.ndarray(declared.shape, dtype=dtype, buffer=buffer, order="F")


def _through_nibabel(
    path: Path, declared: Declared
) -> tuple[np.ndarray, np.ndarray, list[str], tuple[float, float], str]:
    """nibabel's reading: (voxels, RAS affine, notes, (slope, intercept), description)."""
    from nibabel.filebasedimages import ImageFileError
    from nibabel.spatialimages import HeaderDataError

    try:
        with _nibabel_notes() as said:
            img = _load(path, declared)
            data, notes = _voxels(path, img)
            affine = img.affine
    except (*TRUNCATION_ERRORS, OSError) as exc:  # nibabel: "Expected 240 bytes, got 191"
        raise truncated(path, _first_line(exc)) from exc
    except (ImageFileError, HeaderDataError) as exc:
        raise UnreadableVolume(
            f"{path.name}: nibabel cannot read this NIfTI header ({_first_line(exc)}); re-export "
            "the volume from the program that wrote it."
        ) from exc
    notes += said + _orientation_notes(img)
    return data, affine, notes, _scaling(img), _description(img)


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

    if path.name.lower().endswith(".gz") == gzipped(path) or declared.pair:
        return cast("nib.Nifti1Image", nib.load(path, mmap=False))  # sniffed: a NIfTI
    klass = nib.Nifti2Image if declared.version == 2 else nib.Nifti1Image
    with open_stream(path) as stream:
        content = io.BytesIO(stream.read(declared.needed))
    holder = nib.FileHolder(filename=str(path), fileobj=content)
    return klass.from_file_map({"image": holder, "header": holder}, mmap=False)


def _looks_like_ct(data: np.ndarray, description: str) -> str:
    """Why the volume is taken as CT in HU ('' when it is not).

    NIfTI has no modality field, but bone and skin presets need to know HU: trust a
    description that says so, else air at about -1000 (or a -2048/-3024 pad) with tissue above 0 is CT.
    """
    return _ct_reason(float(np.min(data)), float(np.max(data)), description)


def _ct_reason(lo: float, hi: float, description: str) -> str:
    """:func:`_looks_like_ct` of a volume whose values span lo..hi."""
    words = description.upper().split()
    if "HU" in words or "CT" in words:
        return f"the header description says {description!r}"
    if -3100.0 <= lo <= -900.0 and hi > 100.0:  # some scanners pad outside the FOV at -2048/-3024
        return f"air at {lo:g}, as CT stores it"
    return ""


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


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
