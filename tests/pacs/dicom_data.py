"""DICOM objects for the PACS tests: a small CT series, DICOM SEGs and an RT-STRUCT.

Plain functions that take an output folder and return what they wrote, so that the
segmentation readers' tests and the Orthanc tests (STOW the files, then import them)
use the same objects:

- :func:`write_seg`: a real DICOM SEG (highdicom, BINARY) of the abdomen CT in
  ``ct_abdomen_totalseg/dicom`` from TotalSegmentator's labels for it
  (``example_seg_dicom.nii.gz``), named and coloured after TotalSegmentator;
- :func:`write_ct_series`: a synthetic CT series (uncompressed, no data set needed);
- :func:`write_small_seg`: a SEG of given masks over any series (BINARY or FRACTIONAL);
- :func:`write_rtstruct`: an RT Structure Set over any series whose ROIs are analytic
  shapes in patient mm (:func:`rtstruct_rois` gives them and their volumes in mL).

Voxel arrays here are (X, Y, Z) = (column, row, slice), like MISS volumes; affines map
voxel indices to LPS mm.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

REPO = Path(__file__).resolve().parents[2]
DATASETS = Path(os.environ.get("MISS_DATASETS", REPO.parent / "shared" / "datasets"))
ABDOMEN = "ct_abdomen_totalseg"
CT_IMAGE_STORAGE = "1.2.840.10008.5.1.4.1.1.2"
RT_STRUCTURE_SET_STORAGE = "1.2.840.10008.5.1.4.1.1.481.3"
#: SNOMED CT: segmented property category and type of every segment written here.
ANATOMICAL_STRUCTURE = ("123037004", "SCT", "Anatomical Structure")


# --------------------------------------------------------------------------- series


def read_series(series_dir: Path) -> tuple[list[Dataset], np.ndarray]:
    """The image series in a folder, sorted along the slice normal, and its affine.

    Returns
    -------
    slices : list of Dataset
        Headers and pixels, first slice first.
    affine : (4, 4) float64
        Voxel (column, row, slice) to LPS mm.
    """
    slices = [pydicom.dcmread(p) for p in sorted(Path(series_dir).iterdir()) if p.is_file()]
    return sort_series(slices)


def sort_series(slices: list[Dataset]) -> tuple[list[Dataset], np.ndarray]:
    """:func:`read_series` of datasets already read (e.g. changed in memory)."""
    slices = [s for s in slices if "ImagePositionPatient" in s]
    for s in slices:  # the abdomen CT keeps its SOP class only in the file meta
        if not s.get("SOPClassUID"):
            s.SOPClassUID = s.file_meta.MediaStorageSOPClassUID
        if not s.get("SOPInstanceUID"):
            s.SOPInstanceUID = s.file_meta.MediaStorageSOPInstanceUID
    cosines = np.array(slices[0].ImageOrientationPatient, dtype=float)
    normal = np.cross(cosines[:3], cosines[3:])
    slices.sort(key=lambda s: float(np.dot(normal, np.array(s.ImagePositionPatient, float))))
    first = np.array(slices[0].ImagePositionPatient, float)
    last = np.array(slices[-1].ImagePositionPatient, float)
    row_mm, col_mm = (float(v) for v in slices[0].PixelSpacing)
    affine = np.eye(4)
    affine[:3, 0] = cosines[:3] * col_mm
    affine[:3, 1] = cosines[3:] * row_mm
    affine[:3, 2] = (last - first) / max(len(slices) - 1, 1) if len(slices) > 1 else normal
    affine[:3, 3] = first
    return slices, affine


def write_ct_series(
    out_dir: Path,
    dims: tuple[int, int, int] = (64, 56, 12),
    spacing: tuple[float, float, float] = (0.8, 0.8, 2.5),
    origin: tuple[float, float, float] = (-25.0, -22.0, -14.0),
) -> list[Path]:
    """A synthetic axial CT series: a water cylinder (0 HU) in air (-1000 HU).

    ``dims`` (columns, rows, slices), ``spacing`` mm (column, row, slice), ``origin`` the
    first voxel's centre in LPS mm. Returns the files, first slice first.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    study, series, frame = generate_uid(), generate_uid(), generate_uid()
    cols, rows, count = dims
    x = origin[0] + spacing[0] * np.arange(cols)
    y = origin[1] + spacing[1] * np.arange(rows)
    inside = (x[None, :] - x.mean()) ** 2 + (y[:, None] - y.mean()) ** 2 < (0.4 * np.ptp(x)) ** 2
    pixels = np.where(inside, 1024, 24).astype(np.uint16)  # stored value = HU + 1024
    paths = []
    for k in range(count):
        ds = _image_header(CT_IMAGE_STORAGE, "CT", study, series, frame)
        ds.InstanceNumber = k + 1
        ds.ImagePositionPatient = [origin[0], origin[1], origin[2] + k * spacing[2]]
        ds.ImageOrientationPatient = [1, 0, 0, 0, 1, 0]
        ds.PixelSpacing = [spacing[1], spacing[0]]
        ds.SliceThickness = spacing[2]
        ds.Rows, ds.Columns = rows, cols
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 12, 11, 0
        ds.RescaleIntercept, ds.RescaleSlope, ds.RescaleType = -1024, 1, "HU"
        ds.PixelData = pixels.tobytes()
        paths.append(_save(ds, out_dir / f"CT{k + 1:03d}.dcm"))
    return paths


def _image_header(sop_class: str, modality: str, study: str, series: str, frame: str) -> Dataset:
    ds = Dataset()
    ds.SOPClassUID, ds.SOPInstanceUID = sop_class, generate_uid()
    ds.Modality = modality
    ds.PatientName, ds.PatientID = "MISS^Phantom", "MISS-PHANTOM"
    ds.PatientBirthDate, ds.PatientSex = "", "O"
    ds.StudyInstanceUID, ds.SeriesInstanceUID, ds.FrameOfReferenceUID = study, series, frame
    ds.StudyDate, ds.StudyTime, ds.StudyID, ds.AccessionNumber = "20260101", "120000", "1", ""
    ds.ReferringPhysicianName, ds.SeriesNumber = "", 1
    ds.PositionReferenceIndicator = ""
    ds.Manufacturer = "MISS tests"
    return ds


def _save(ds: Dataset, path: Path) -> Path:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ds.SOPClassUID
    meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds.file_meta = meta
    ds.save_as(path, enforce_file_format=True)
    return path


# --------------------------------------------------------------------------- SEG


def write_seg(
    out_dir: Path, datasets: Path = DATASETS, slices: list[Dataset] | None = None
) -> Path:
    """A DICOM SEG (BINARY) of the abdomen CT with TotalSegmentator's 31 labels.

    Segment numbers are 1..31 in the order of TotalSegmentator's label ids; each
    segment's label is TotalSegmentator's name and its colour MISS's TotalSegmentator
    colour. Same study as the CT, references every CT slice. About 2 s. ``slices``: the
    CT as read and changed in memory (a PACS's copy with its own UIDs), else as on disk.
    """
    import nibabel as nib

    from miss.structures.labels import totalsegmentator_table

    folder = datasets / ABDOMEN
    slices, affine = sort_series(slices) if slices else read_series(folder / "dicom")
    nifti = nib.load(folder / "example_seg_dicom.nii.gz")
    ras_to_lps = np.diag([-1.0, -1.0, 1.0, 1.0])
    labels = _resample(np.asarray(nifti.dataobj), ras_to_lps @ nifti.affine, affine, _dims(slices))
    table = totalsegmentator_table()
    present = [int(v) for v in np.unique(labels) if v]
    masks = {table[v].name: labels == v for v in present}
    colors = {table[v].name: table[v].color or (0.5, 0.5, 0.5) for v in present}
    return write_small_seg(
        slices, out_dir, masks, colors=colors, algorithm="TotalSegmentator", name="seg.dcm"
    )


def _dims(slices: list[Dataset]) -> tuple[int, int, int]:
    return int(slices[0].Columns), int(slices[0].Rows), len(slices)


def _resample(
    data: np.ndarray, data_affine: np.ndarray, grid_affine: np.ndarray, dims: tuple[int, ...]
) -> np.ndarray:
    """Nearest-neighbour labels of ``data`` at each grid voxel's centre (LPS mm)."""
    from scipy import ndimage

    to_data = np.linalg.inv(data_affine) @ grid_affine
    return ndimage.affine_transform(
        data, to_data[:3, :3], offset=to_data[:3, 3], output_shape=dims, order=0, cval=0
    )


def write_small_seg(
    series: Path | list[Dataset],
    out_dir: Path,
    masks: dict[str, np.ndarray],
    *,
    fractional: bool = False,
    colors: dict[str, tuple[float, float, float]] | None = None,
    algorithm: str = "MISS tests",
    name: str = "seg.dcm",
) -> Path:
    """A SEG of ``masks`` (name -> (X, Y, Z) bool, or floats 0..1 when ``fractional``)
    over a series, segment numbers 1.. in the dict's order; colours as sRGB fractions."""
    import highdicom as hd
    from pydicom.sr.codedict import codes

    slices = read_series(series)[0] if isinstance(series, Path) else series
    stack = np.stack([np.asarray(m) for m in masks.values()], axis=-1)  # (X, Y, Z, S)
    pixels = np.ascontiguousarray(stack.transpose(2, 1, 0, 3))  # (frames, rows, cols, S)
    pixels = pixels.astype(np.float32 if fractional else bool)
    category = hd.sr.CodedConcept(*ANATOMICAL_STRUCTURE)
    algorithm_id = hd.AlgorithmIdentificationSequence(
        name=algorithm, family=codes.cid7162.ArtificialIntelligence, version="1"
    )
    descriptions = []
    for number, segment in enumerate(masks, 1):
        rgb = (colors or {}).get(segment)
        descriptions.append(
            hd.seg.SegmentDescription(
                segment_number=number,
                segment_label=segment,
                segmented_property_category=category,
                segmented_property_type=category,
                algorithm_type="AUTOMATIC",
                algorithm_identification=algorithm_id,
                display_color=hd.color.CIELabColor.from_rgb(*(round(c * 255) for c in rgb))
                if rgb
                else None,
            )
        )
    seg = hd.seg.Segmentation(
        source_images=slices,
        pixel_array=pixels,
        segmentation_type="FRACTIONAL" if fractional else "BINARY",
        segment_descriptions=descriptions,
        series_instance_uid=generate_uid(),
        series_number=100,
        sop_instance_uid=generate_uid(),
        instance_number=1,
        manufacturer="MISS tests",
        manufacturer_model_name="tests/pacs/dicom_data.py",
        software_versions="1",
        device_serial_number="1",
        series_description=f"{algorithm} segmentation",
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / name
    seg.save_as(path)
    return path


# --------------------------------------------------------------------------- RT-STRUCT


@dataclass(frozen=True)
class Roi:
    """One analytic ROI: planar contours (each an (N, 3) LPS mm polygon) and its volume."""

    number: int
    name: str
    color: tuple[int, int, int]
    contours: list[np.ndarray]
    ml: float


def rtstruct_rois(affine: np.ndarray, dims: tuple[int, int, int]) -> list[Roi]:
    """Three shapes inside the grid, in patient mm, with their volumes in mL:

    - ``box``: an axis-aligned box, edges half-way between voxel centres;
    - ``cylinder``: a stack of discs (128-gons) of radius 10 voxels;
    - ``tube``: a disc with a hole (two contours per slice: the even-odd rule makes the
      inner one a hole), its contours 0.3 slice above the slice centres (nearest slice).

    Each shape's height is its number of slices times the slice spacing (the slab each
    contour stands for), so the volumes are exact up to the voxelisation of the outline.
    """
    step = np.linalg.norm(affine[:3, :3], axis=0)
    dx, dy, dz = (float(s) for s in step)

    def at(i: float, j: float, k: float) -> np.ndarray:
        return (affine @ np.array([i, j, k, 1.0]))[:3]

    ks = range(2, dims[2] - 2)
    height = len(ks) * dz
    box = []
    for k in ks:
        corners = [(3.5, 4.5), (13.5, 4.5), (13.5, 12.5), (3.5, 12.5)]
        box.append(np.array([at(i, j, k) for i, j in corners]))
    box_ml = (10 * dx) * (8 * dy) * height / 1000

    def disc(ci: float, cj: float, radius: float, k: float) -> np.ndarray:
        t = np.linspace(0, 2 * math.pi, 128, endpoint=False)
        centre = at(ci, cj, k)
        points = centre + radius * np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], axis=1)
        return points

    r = 10 * min(dx, dy)
    polygon = 0.5 * 128 * math.sin(2 * math.pi / 128)  # area of a unit-radius 128-gon
    cylinder = [disc(dims[0] * 0.75, dims[1] * 0.22, r, k) for k in ks]
    cylinder_ml = polygon * r * r * height / 1000
    r_out, r_in = 0.2 * min(dims[0] * dx, dims[1] * dy), 0.08 * min(dims[0] * dx, dims[1] * dy)
    tube = []
    for k in ks:
        tube += [disc(dims[0] * 0.4, dims[1] * 0.64, r_out, k + 0.3)]
        tube += [disc(dims[0] * 0.4, dims[1] * 0.64, r_in, k + 0.3)]
    tube_ml = polygon * (r_out**2 - r_in**2) * height / 1000
    return [
        Roi(1, "box", (220, 40, 40), box, box_ml),
        Roi(2, "cylinder", (40, 200, 60), cylinder, cylinder_ml),
        Roi(3, "tube", (50, 90, 230), tube, tube_ml),
    ]


def write_rtstruct(
    series_dir: Path, out_dir: Path, rois: list[Roi] | None = None, name: str = "rtstruct.dcm"
) -> Path:
    """An RT Structure Set over the series in ``series_dir`` (same study and frame of
    reference, references every slice); ``rois`` default to :func:`rtstruct_rois`."""
    slices, affine = read_series(series_dir)
    first = slices[0]
    if rois is None:
        rois = rtstruct_rois(affine, _dims(slices))
    ds = _image_header(
        RT_STRUCTURE_SET_STORAGE,
        "RTSTRUCT",
        first.StudyInstanceUID,
        generate_uid(),
        first.FrameOfReferenceUID,
    )
    for keyword in ("PatientName", "PatientID", "PatientBirthDate", "PatientSex", "StudyDate"):
        if keyword in first:
            setattr(ds, keyword, first.data_element(keyword).value)
    del ds.FrameOfReferenceUID  # an RT-STRUCT names it in its referenced-frame sequence
    ds.SeriesNumber, ds.InstanceNumber = 101, 1
    ds.StructureSetLabel, ds.StructureSetDate, ds.StructureSetTime = "MISS", "20260101", "1200"
    images = Sequence([_item(ReferencedSOPClassUID=s.SOPClassUID,
                             ReferencedSOPInstanceUID=s.SOPInstanceUID) for s in slices])  # fmt: skip
    series = _item(SeriesInstanceUID=first.SeriesInstanceUID, ContourImageSequence=images)
    study = _item(
        ReferencedSOPClassUID="1.2.840.10008.3.1.2.3.1",  # Detached Study Management (retired)
        ReferencedSOPInstanceUID=first.StudyInstanceUID,
        RTReferencedSeriesSequence=Sequence([series]),
    )
    ds.ReferencedFrameOfReferenceSequence = Sequence(
        [
            _item(
                FrameOfReferenceUID=first.FrameOfReferenceUID,
                RTReferencedStudySequence=Sequence([study]),
            )
        ]  # fmt: skip
    )
    ds.StructureSetROISequence = Sequence(
        [
            _item(
                ROINumber=roi.number,
                ReferencedFrameOfReferenceUID=first.FrameOfReferenceUID,
                ROIName=roi.name,
                ROIGenerationAlgorithm="MANUAL",
            )
            for roi in rois
        ]  # fmt: skip
    )
    ds.ROIContourSequence = Sequence([_roi_contours(roi) for roi in rois])
    ds.RTROIObservationsSequence = Sequence(
        [
            _item(
                ObservationNumber=roi.number,
                ReferencedROINumber=roi.number,
                RTROIInterpretedType="ORGAN",
                ROIInterpreter="",
            )
            for roi in rois
        ]  # fmt: skip
    )
    out_dir.mkdir(parents=True, exist_ok=True)
    return _save(ds, out_dir / name)


def _roi_contours(roi: Roi) -> Dataset:
    contours = [
        _item(
            ContourGeometricType="CLOSED_PLANAR",
            NumberOfContourPoints=len(points),
            ContourData=[f"{v:.4f}" for v in points.ravel()],
        )
        for points in roi.contours
    ]
    return _item(
        ReferencedROINumber=roi.number,
        ROIDisplayColor=list(roi.color),
        ContourSequence=Sequence(contours),
    )


def _item(**elements: object) -> Dataset:
    ds = Dataset()
    for keyword, value in elements.items():
        setattr(ds, keyword, value)
    return ds
