"""DICOM segmentations as label maps: DICOM SEG and RT Structure Sets (RT-STRUCT).

A segmentation stored beside an image series in a PACS becomes a label map over that
series, with the names and colours it carries:

- :func:`read_seg`: a DICOM SEG (BINARY or FRACTIONAL, read with highdicom) on its own
  grid; label = segment number, name = SegmentLabel, colour =
  RecommendedDisplayCIELabValue in sRGB. FRACTIONAL segments are thresholded at 0.5 of
  their maximum. Where segments overlap the higher segment number wins (as highdicom
  does when it combines segments), and the volume's ``meta["notes"]`` says how many
  voxels that decided.
- :func:`read_rtstruct`: each ROI's CLOSED_PLANAR contours rasterised on the grid of the
  image series they were drawn on (voxel centres inside by the even-odd rule, so an
  inner contour is a hole; a contour between two slices goes to the nearest one); labels
  1..N in ROINumber order, names from ROIName, colours from ROIDisplayColor. Where ROIs
  overlap the later one wins.
- :func:`segmentation_kind` sniffs the SOP class from the header alone.

Both readers are given untrusted files: sizes are checked against :data:`MAX_VOXELS`
and :data:`MAX_CONTOUR_POINTS` before anything is allocated, and every refusal is an
:class:`~miss.errors.UnreadableSegmentation` (or ``InputTooLarge``) naming the fix.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Literal

import numpy as np

from miss.errors import InputTooLarge, UnreadableSegmentation
from miss.io import codecs
from miss.structures.labels import LabelInfo, LabelTable
from miss.types import Volume

SEG_STORAGE = "1.2.840.10008.5.1.4.1.1.66.4"
RTSTRUCT_STORAGE = "1.2.840.10008.5.1.4.1.1.481.3"
#: SOP classes read here, by what they are.
KINDS: dict[str, Literal["seg", "rtstruct"]] = {SEG_STORAGE: "seg", RTSTRUCT_STORAGE: "rtstruct"}
#: Largest label map either reader makes (uint16: 2 bytes a voxel) and largest number of
#: SEG pixels (frames x rows x columns) it decodes: a 512 x 512 x 1024 CT is 2^28.
MAX_VOXELS = 1 << 28
MAX_FRAME_PIXELS = 1 << 31
#: Most contour points an RT-STRUCT may hold (a fine whole-body plan has about 10^6).
MAX_CONTOUR_POINTS = 20_000_000
#: Label numbers are stored as uint16, 0 being the background.
MAX_LABEL = 65535
#: How far (in slices) a contour's points may stray from one image plane.
PLANE_TOLERANCE = 0.25


def segmentation_kind(path: str | os.PathLike[str]) -> Literal["seg", "rtstruct"] | None:
    """``"seg"`` or ``"rtstruct"`` from a DICOM file's SOP Class UID (header only), or
    None for anything else: another DICOM object, not DICOM, unreadable."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    _check_deflated(Path(path))
    try:
        header = pydicom.dcmread(
            path, stop_before_pixels=True, specific_tags=["SOPClassUID"], force=False
        )
    except (InvalidDicomError, OSError, ValueError, TypeError, AttributeError, EOFError):
        return None
    return KINDS.get(_sop_class(header))


def _check_deflated(path: Path) -> None:
    """A deflated data set past the caps of :mod:`miss.io.codecs` is refused before
    pydicom inflates it whole (it does, for the header alone)."""
    try:
        stream = path.open("rb")
    except OSError:
        return  # pydicom says why it cannot be read
    with stream:
        codecs.check_deflated_dicom(path, stream)


def _sop_class(header: Any) -> str:
    """The dataset's SOP Class UID, else the file meta's (some exports keep only that)."""
    uid = str(header.get("SOPClassUID", "") or "")
    if not uid and getattr(header, "file_meta", None) is not None:
        uid = str(header.file_meta.get("MediaStorageSOPClassUID", "") or "")
    return uid


def find_segmentation(folder: Path) -> Path:
    """The one SEG or RT-STRUCT file in ``folder`` (searched recursively)."""
    found = sorted(p for p in folder.rglob("*") if p.is_file() and segmentation_kind(p))
    if not found:
        raise UnreadableSegmentation(
            "no DICOM SEG or RT-STRUCT object found among the files; send the segmentation "
            "object itself (SOP class 1.2.840.10008.5.1.4.1.1.66.4 or ...481.3)."
        )
    if len(found) > 1:
        names = ", ".join(p.name for p in found[:5])
        raise UnreadableSegmentation(
            f"several segmentation objects found ({names}); import one at a time."
        )
    return found[0]


# --------------------------------------------------------------------------- DICOM SEG


def read_seg(path: str | os.PathLike[str]) -> tuple[Volume, LabelTable]:
    """Read a DICOM SEG as a label map.

    Returns
    -------
    labels : Volume
        ``data`` (X, Y, Z) uint16, Fortran order, 0 = background, else the segment
        number; ``affine`` voxel to LPS mm (the SEG's own grid: its frames' positions).
    table : dict of int to LabelInfo
        Per segment number: SegmentLabel, and the recommended display colour as sRGB
        fractions (None when the SEG gives none).
    """
    name = Path(path).name
    header = _header(path, "seg", "a DICOM SEG")
    _check_seg_size(header, name)
    pixels = int(header.get("NumberOfFrames", 1) or 1) * int(header.Rows) * int(header.Columns)
    codecs.check_decoded(Path(path), pixels, Path(path).stat().st_size, "SEG pixel data")
    seg = _segread(path, name)
    geometry = _seg_geometry(seg, name)
    numbers = [int(n) for n in seg.segment_numbers]
    if max(numbers) > MAX_LABEL:
        raise UnreadableSegmentation(f"{name}: segment numbers above {MAX_LABEL} are invalid.")
    data, overlap = _combine(seg, numbers, geometry.spatial_shape, name)
    if not data.any():
        raise UnreadableSegmentation(
            f"{name}: every segment is empty (no voxel set); export the segmentation again."
        )
    notes = ["DICOM SEG read with highdicom"]
    if overlap:
        notes.append(f"{overlap} voxels in several segments: the higher segment number kept")
    meta = {
        "source_format": "DICOM SEG",
        "modality": "SEG",
        "segmentation_type": str(seg.SegmentationType),
        "notes": notes,
    }
    # highdicom indexes (slice, row, column); MISS (column, row, slice).
    affine = np.asarray(geometry.affine, dtype=np.float64)[:, [2, 1, 0, 3]]
    return Volume(data.transpose(2, 1, 0), affine, meta=meta), _seg_table(seg, numbers)


def _header(path: str | os.PathLike[str], kind: str, what: str) -> Any:
    """The file's header (no pixels), checked to be ``kind``."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    name = Path(path).name
    _check_deflated(Path(path))
    try:
        header = pydicom.dcmread(path, stop_before_pixels=True)
        for _ in header.iterall():  # pydicom parses sequences when first touched
            pass
    except (FileNotFoundError, PermissionError, IsADirectoryError) as exc:
        raise UnreadableSegmentation(f"{name}: cannot read it ({exc.strerror}).") from None
    except (InvalidDicomError, OSError, EOFError, ValueError, TypeError, AttributeError) as exc:
        raise UnreadableSegmentation(
            f"{name} is not a readable DICOM file ({_short(exc)}); it is damaged or "
            f"truncated: export {what} again."
        ) from None
    found = KINDS.get(_sop_class(header))
    if found != kind:
        sop = _sop_class(header) or "none"
        hint = {"seg": "a DICOM SEG", "rtstruct": "an RT-STRUCT"}.get(found or "", "")
        raise UnreadableSegmentation(
            f"{name} is not {what} (its SOP class is {sop}"
            + (f", it is {hint}" if hint else ", e.g. an image")
            + f"); give {what} object of the series, not one of its images."
        )
    return header


def _short(exc: BaseException) -> str:
    return str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__


def _check_seg_size(header: Any, name: str) -> None:
    """Refuse an empty or oversized SEG from its header, before any pixel is decoded."""
    if not header.get("SegmentSequence"):
        raise UnreadableSegmentation(
            f"{name} holds no segments (its SegmentSequence is empty); export the "
            "segmentation again with at least one segment."
        )
    try:
        frames = int(header.get("NumberOfFrames", 1) or 1)
        pixels = frames * int(header.Rows) * int(header.Columns)
    except (AttributeError, TypeError, ValueError):
        raise UnreadableSegmentation(
            f"{name} has no usable Rows/Columns/NumberOfFrames; export it again."
        ) from None
    if pixels > MAX_FRAME_PIXELS:
        raise InputTooLarge(
            f"{name} holds {frames} frames of {header.Rows} x {header.Columns} pixels, more "
            f"than the {MAX_FRAME_PIXELS} pixels read here; send fewer segments or a "
            "smaller region."
        )


#: What highdicom and pydicom raise on a damaged or incomplete SEG.
_DAMAGED = (
    ValueError, TypeError, KeyError, AttributeError, IndexError, RuntimeError, EOFError, OSError,
)  # fmt: skip


def _segread(path: str | os.PathLike[str], name: str) -> Any:
    from highdicom.seg import segread

    try:
        return segread(path)
    except _DAMAGED as exc:
        raise UnreadableSegmentation(
            f"{name} is a damaged DICOM SEG ({_short(exc)}); export it again."
        ) from None


def _seg_geometry(seg: Any, name: str) -> Any:
    """The regular grid the SEG's frames lie on (highdicom's VolumeGeometry)."""
    try:
        geometry = seg.get_volume_geometry(allow_missing_positions=True)
    except _DAMAGED as exc:
        geometry, reason = None, _short(exc)
    else:
        reason = "its frames do not lie on a regular grid of parallel planes"
    if geometry is None:
        raise UnreadableSegmentation(
            f"{name}: no 3-D geometry ({reason}); MISS needs a SEG whose frames carry "
            "plane positions and orientation, e.g. one made over a CT or MR series."
        )
    if math.prod(geometry.spatial_shape) > MAX_VOXELS:
        raise InputTooLarge(
            f"{name} spans {geometry.spatial_shape} voxels, more than {MAX_VOXELS}; send a "
            "segmentation of a smaller region."
        )
    return geometry


def _combine(
    seg: Any, numbers: list[int], shape: tuple[int, int, int], name: str
) -> tuple[np.ndarray, int]:
    """(slice, row, column) uint16 map of all segments, higher numbers on top, and the
    number of voxels more than one segment claimed. One segment at a time, so memory is
    the map plus one segment's mask."""
    fractional = str(seg.SegmentationType) == "FRACTIONAL"
    out = np.zeros(shape, dtype=np.uint16)
    overlap = 0
    for number in sorted(numbers):
        try:
            volume = seg.get_volume(
                segment_numbers=[number], rescale_fractional=True, allow_missing_positions=True
            )
        except _DAMAGED as exc:
            raise UnreadableSegmentation(
                f"{name}: segment {number} cannot be read ({_short(exc)}); export it again."
            ) from None
        if tuple(volume.spatial_shape) != tuple(shape):
            raise UnreadableSegmentation(
                f"{name}: segment {number} lies on another grid than the others; export "
                "the segments over one image series."
            )
        values = volume.array.reshape(shape)
        mask = values >= 0.5 if fractional else values > 0
        overlap += int(np.count_nonzero(out[mask]))
        out[mask] = number
    return out, overlap


def _seg_table(seg: Any, numbers: list[int]) -> LabelTable:
    table: LabelTable = {}
    for number in numbers:
        item = seg.get_segment_description(number)
        label = str(getattr(item, "segment_label", "") or "").strip()[:200]
        table[number] = LabelInfo(label or f"segment {number}", _lab_to_srgb(item))
    return table


def _lab_to_srgb(item: Any) -> tuple[float, float, float] | None:
    """RecommendedDisplayCIELabValue (DICOM's scaled 16-bit L*a*b*, D65) as sRGB
    fractions, through highdicom's ``CIELabColor.to_rgb``; None when absent or invalid."""
    from highdicom.color import CIELabColor

    value = item.get("RecommendedDisplayCIELabValue")
    if value is None or len(value) != 3:
        return None
    try:
        red, green, blue = CIELabColor.from_dicom_value([int(v) for v in value]).to_rgb()
    except (ValueError, TypeError):
        return None
    return (red / 255, green / 255, blue / 255)


# --------------------------------------------------------------------------- RT-STRUCT


def read_rtstruct(path: str | os.PathLike[str], grid: Volume) -> tuple[Volume, LabelTable]:
    """Rasterise an RT Structure Set's ROIs onto the grid of the image series.

    Parameters
    ----------
    path : path
        The RT-STRUCT file.
    grid : Volume
        The referenced image series as stored (only its ``affine``, voxel to LPS mm, and
        ``dims`` are used; its voxels are never read).

    Returns
    -------
    labels : Volume
        (X, Y, Z) uint16 on ``grid``'s dims and affine: ROI ``n`` (in ROINumber order,
        1-based) where a voxel centre lies inside an odd number of its contours on that
        slice.
    table : dict of int to LabelInfo
        ROIName and ROIDisplayColor (sRGB fractions) per label.
    """
    name = Path(path).name
    header = _header(path, "rtstruct", "an RT-STRUCT")
    rois = _rois(header, name)
    if math.prod(grid.dims) > MAX_VOXELS:
        raise InputTooLarge(f"the image grid {grid.dims} is larger than {MAX_VOXELS} voxels.")
    to_index = np.linalg.inv(grid.affine)
    out = np.zeros(grid.dims, dtype=np.uint16, order="F")
    table: LabelTable = {}
    for label, (roi_name, color, contours) in enumerate(rois, 1):
        table[label] = LabelInfo(roi_name, color)
        mask = _rasterise(contours, to_index, grid.dims, f"{name}, ROI {roi_name!r}")
        out[mask] = label
    if not out.any():
        raise UnreadableSegmentation(
            f"{name}: no contour covers a voxel centre of the image series; check that the "
            "RT-STRUCT belongs to this series (same frame of reference)."
        )
    meta = {"source_format": "RT-STRUCT", "modality": "RTSTRUCT", "notes": ["contours rasterised"]}
    return Volume(out, grid.affine, meta=meta), table


def _rois(header: Any, name: str) -> list[tuple[str, Any, list[np.ndarray]]]:
    """(name, sRGB colour or None, closed planar contours as (N, 3) mm) per ROI, in
    ROINumber order."""
    declared = {}
    for item in header.get("StructureSetROISequence") or []:
        try:
            declared[int(item.ROINumber)] = str(item.get("ROIName", "") or "").strip()[:200]
        except (AttributeError, TypeError, ValueError):
            continue
    if not declared:
        raise UnreadableSegmentation(
            f"{name} declares no ROIs (StructureSetROISequence is empty); export the "
            "structure set again with its structures."
        )
    if len(declared) > MAX_LABEL:
        raise UnreadableSegmentation(f"{name} declares more than {MAX_LABEL} ROIs.")
    drawn = {}
    points = 0
    for item in header.get("ROIContourSequence") or []:
        number = int(item.get("ReferencedROINumber", -1))
        color = item.get("ROIDisplayColor")
        rgb = tuple(min(max(float(c), 0.0), 255.0) / 255 for c in color) if color else None
        contours = [c for c in item.get("ContourSequence") or [] if _closed_planar(c)]
        points += sum(len(c.get("ContourData") or ()) // 3 for c in contours)
        if points > MAX_CONTOUR_POINTS:
            raise InputTooLarge(
                f"{name} holds more than {MAX_CONTOUR_POINTS} contour points; send fewer ROIs."
            )
        drawn[number] = (rgb if rgb and len(rgb) == 3 else None, contours)
    rois = []
    for number in sorted(declared):
        color, contours = drawn.get(number, (None, []))
        arrays = [_contour_points(c, name, number) for c in contours]
        rois.append((declared[number] or f"ROI {number}", color, arrays))
    return rois


def _closed_planar(item: Any) -> bool:
    return str(item.get("ContourGeometricType", "")).upper() == "CLOSED_PLANAR"


def _contour_points(item: Any, name: str, number: int) -> np.ndarray:
    try:
        data = np.array([float(v) for v in item.ContourData], dtype=np.float64)
    except (AttributeError, TypeError, ValueError):
        data = np.zeros(1)
    if data.size < 9 or data.size % 3 or not np.isfinite(data).all():
        raise UnreadableSegmentation(
            f"{name}: a contour of ROI {number} has no usable ContourData (x, y, z triplets "
            "in mm, at least three points); export the structure set again."
        )
    return data.reshape(-1, 3)


def _rasterise(
    contours: list[np.ndarray], to_index: np.ndarray, dims: tuple[int, int, int], what: str
) -> np.ndarray:
    """(X, Y, Z) bool: voxel centres inside an odd number of the ROI's contours on their
    slice."""
    mask = np.zeros(dims, dtype=bool, order="F")
    for points in contours:
        ijk = points @ to_index[:3, :3].T + to_index[:3, 3]
        spread = float(np.ptp(ijk[:, 2]))
        if spread > PLANE_TOLERANCE:
            raise UnreadableSegmentation(
                f"{what}: a contour spans {spread:.2f} slices instead of lying in one image "
                "plane; it was drawn on another series (another orientation): give the "
                "RT-STRUCT of this series, or import the series it references."
            )
        k = round(float(ijk[:, 2].mean()))
        if 0 <= k < dims[2]:
            mask[:, :, k] ^= polygon_mask(ijk[:, :2], dims[:2])
    return mask


def polygon_mask(polygon: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Pixel centres (i, j) inside a polygon, by the even-odd rule.

    Parameters
    ----------
    polygon : (N, 2) float array
        Vertices in pixel indices (i, j), closed implicitly (last to first).
    shape : (X, Y)
        The pixel grid; parts of the polygon outside it are clipped.

    Returns
    -------
    (X, Y) bool array
        Scanline fill: along each row j, a pixel is inside when an odd number of edges
        cross the row at or left of its centre (edges count on [y_min, y_max)).
    """
    x0, y0 = polygon[:, 0], polygon[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    sloped = y0 != y1
    x0, y0, x1, y1 = x0[sloped], y0[sloped], x1[sloped], y1[sloped]
    low = np.clip(np.ceil(np.minimum(y0, y1)), 0, shape[1]).astype(np.int64)
    high = np.clip(np.ceil(np.maximum(y0, y1)), 0, shape[1]).astype(np.int64)
    rows_per_edge = high - low
    edge = np.repeat(np.arange(len(low)), rows_per_edge)
    first = np.cumsum(rows_per_edge) - rows_per_edge  # each edge's first crossing
    row = low[edge] + np.arange(int(rows_per_edge.sum())) - first[edge]
    x = x0[edge] + (row - y0[edge]) * (x1[edge] - x0[edge]) / (y1[edge] - y0[edge])
    start = np.clip(np.ceil(x), 0, shape[0]).astype(np.int64)
    crossings = np.zeros((shape[0] + 1, shape[1]), dtype=np.int32)
    np.add.at(crossings, (start, row), 1)
    return (np.cumsum(crossings, axis=0)[: shape[0]] & 1).astype(bool)
