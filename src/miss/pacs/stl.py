"""A model as DICOM Encapsulated STL instances (SOP class 1.2.840.10008.5.1.4.1.1.104.3),
to go back into the patient's study on the PACS.

One instance per part (a scene of skin and bone is two instances, each printable on its
own and titled with its part's name), all in one new series (modality ``M3D``) of the
original study, with the original patient and study attributes from the volume's
identity record. The STL's coordinates are patient LPS millimetres, which is what the
DICOM patient coordinate system is, so each instance names the source series' Frame of
Reference and says its units are mm: a viewer that knows the frame lays the model over
the images exactly. Each instance lists the source images it was made from (Source
Instance Sequence) where the import recorded them.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from datetime import datetime
from typing import Any

ENCAPSULATED_STL = "1.2.840.10008.5.1.4.1.1.104.3"
#: The patient and study attributes copied from the identity record (original values).
PATIENT_STUDY = (
    "PatientName",
    "PatientID",
    "IssuerOfPatientID",
    "PatientBirthDate",
    "PatientSex",
    "StudyDate",
    "StudyTime",
    "StudyID",
    "AccessionNumber",
    "ReferringPhysicianName",
    "StudyDescription",
)
#: Type 2 attributes of the Patient and General Study modules: present, empty if unknown.
TYPE2 = tuple(k for k in PATIENT_STUDY if k not in ("IssuerOfPatientID", "StudyDescription"))


@dataclass(frozen=True)
class Origin:
    """Where the model belongs: the original study, series and frame of reference UIDs,
    the patient attributes, and the source images (SOP class, SOP instance)."""

    study: str
    series: str
    frame_of_reference: str
    patient: Mapping[str, str]
    sources: Sequence[tuple[str, str]] = ()


def _code(value: str, scheme: str, meaning: str) -> Any:
    from pydicom.dataset import Dataset

    code = Dataset()
    code.CodeValue, code.CodingSchemeDesignator, code.CodeMeaning = value, scheme, meaning
    return code


def encapsulate(
    parts: Sequence[tuple[str, bytes]],
    origin: Origin,
    description: str,
    software: str,
    series_number: int = 9801,
) -> list[Any]:
    """One Encapsulated STL dataset per ``(title, stl bytes)`` in ``parts``, in one new
    series of ``origin.study`` described by ``description``."""
    from pydicom.uid import generate_uid

    series_uid = generate_uid()
    now = datetime.now()
    return [
        _instance(title, stl, origin, description, software, series_uid, series_number, i, now)
        for i, (title, stl) in enumerate(parts, start=1)
    ]


def _instance(
    title: str,
    stl: bytes,
    origin: Origin,
    description: str,
    software: str,
    series_uid: str,
    series_number: int,
    number: int,
    now: datetime,
) -> Any:
    from pydicom.dataset import Dataset, FileMetaDataset
    from pydicom.uid import PYDICOM_IMPLEMENTATION_UID, UID, ExplicitVRLittleEndian, generate_uid

    ds = Dataset()
    ds.SpecificCharacterSet = "ISO_IR 192"  # UTF-8: names as the PACS spelled them
    ds.SOPClassUID, ds.SOPInstanceUID = ENCAPSULATED_STL, generate_uid()
    for keyword in TYPE2:
        setattr(ds, keyword, "")
    for keyword in PATIENT_STUDY:
        value = origin.patient.get(keyword, "")
        if value:
            setattr(ds, keyword, value)
    ds.StudyInstanceUID = origin.study
    # Encapsulated Document Series, Manufacturing 3D Model, Frame of Reference
    ds.Modality, ds.SeriesInstanceUID, ds.SeriesNumber = "M3D", series_uid, series_number
    ds.SeriesDescription = description[:64]
    ds.FrameOfReferenceUID = origin.frame_of_reference
    ds.PositionReferenceIndicator = ""
    ds.MeasurementUnitsCodeSequence = [_code("mm", "UCUM", "mm")]
    # General and Enhanced General Equipment
    ds.Manufacturer, ds.ManufacturerModelName = "MISS", "MISS"
    ds.DeviceSerialNumber, ds.SoftwareVersions = "0", software[:64]
    # Encapsulated Document
    ds.InstanceNumber = number
    ds.ContentDate, ds.ContentTime = now.strftime("%Y%m%d"), now.strftime("%H%M%S")
    ds.AcquisitionDateTime = now.strftime("%Y%m%d%H%M%S")
    ds.BurnedInAnnotation = "NO"
    ds.DocumentTitle = title[:64]
    ds.ConceptNameCodeSequence = []
    ds.MIMETypeOfEncapsulatedDocument = "model/stl"
    ds.EncapsulatedDocument = stl + (b"\0" if len(stl) % 2 else b"")
    ds.EncapsulatedDocumentLength = len(stl)
    sources = [_source(c, i) for c, i in origin.sources]
    if sources:
        ds.SourceInstanceSequence = sources
        reference = Dataset()
        reference.SeriesInstanceUID = origin.series
        reference.ReferencedInstanceSequence = [_source(c, i) for c, i in origin.sources]
        ds.ReferencedSeriesSequence = [reference]
    ds.InstanceCreationDate, ds.InstanceCreationTime = ds.ContentDate, ds.ContentTime
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID, meta.MediaStorageSOPInstanceUID = (
        UID(ENCAPSULATED_STL),  # what pydicom makes of the str anyway
        ds.SOPInstanceUID,
    )
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationClassUID = PYDICOM_IMPLEMENTATION_UID
    ds.file_meta = meta
    ds.preamble = b"\0" * 128  # a DICOM file as STOW-RS sends it: preamble and "DICM"
    return ds


def _source(sop_class: str, sop_instance: str) -> Any:
    from pydicom.dataset import Dataset

    item = Dataset()
    item.ReferencedSOPClassUID, item.ReferencedSOPInstanceUID = sop_class, sop_instance
    return item
