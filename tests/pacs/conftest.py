"""A real Orthanc holding real series from ../shared/datasets, sent in with STOW-RS.

Each series is given a made-up patient (name, ID, birth date, accession number) on its
way in, so that the tests can search by them and check that none of it reaches what
MISS shares. The files in ../shared are never changed.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from pacs import orthanc as orthanc_mod

#: The made-up patients: folder in ../shared/datasets -> (name, ID, birth date, accession).
PATIENTS = {
    "ct_head_dicom_ge_gantrytilt": ("DOE^JANE", "MISS-PT-0001", "19610203", "ACC7001"),
    "ct_abdomen_totalseg/dicom": ("ROE^RICHARD", "MISS-PT-0002", "19750817", "ACC7002"),
    "mr_head_dicom_vsseg001_t1": ("POE^EDGAR", "MISS-PT-0003", "19490119", "ACC7003"),
}


ABDOMEN = "ct_abdomen_totalseg/dicom"


@dataclass
class Series:
    """A series as the PACS holds it: its patient and its original UIDs."""

    folder: str
    patient_name: str
    patient_id: str
    accession: str
    study: str
    series: str
    frame_of_reference: str
    instances: int
    segmentation: str = ""


def read_series(folder: Path, patient: tuple[str, str, str, str]) -> list:
    """The series' datasets with the made-up patient put in (in memory only). A series
    whose files carry no study or series UID (the abdomen CT) gets fixed ones, as a PACS
    would have given it."""
    import pydicom
    from pydicom.uid import generate_uid

    name, pid, birth, accession = patient
    datasets = []
    for path in sorted(p for p in folder.iterdir() if p.is_file()):
        try:
            ds = pydicom.dcmread(path)
        except pydicom.errors.InvalidDicomError:
            continue
        ds.PatientName, ds.PatientID, ds.PatientBirthDate = name, pid, birth
        ds.AccessionNumber = accession
        if not ds.get("SOPClassUID"):  # the abdomen CT keeps it only in the file meta
            ds.SOPClassUID = ds.file_meta.MediaStorageSOPClassUID
        for key in ("StudyInstanceUID", "SeriesInstanceUID", "SOPInstanceUID"):
            if not ds.get(key):
                one = path.name if key == "SOPInstanceUID" else ""
                setattr(ds, key, generate_uid(entropy_srcs=[folder.name, key, one]))
                if key == "SOPInstanceUID":
                    ds.file_meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
        datasets.append(ds)
    return datasets


#: A header the tests' own STOW-RS requests carry, so that a PACS filter can tell them apart.
SETUP_HEADER = "X-Miss-Test-Setup"


def stow(orthanc: orthanc_mod.Orthanc, datasets: list) -> None:
    from dicomweb_client import DICOMwebClient

    client = DICOMwebClient(orthanc.dicomweb, headers={SETUP_HEADER: "1"})
    client._session.auth = (orthanc.user, orthanc.password)
    for start in range(0, len(datasets), 40):
        client.store_instances(datasets[start : start + 40])


@pytest.fixture(scope="session")
def orthanc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[orthanc_mod.Orthanc]:
    why = orthanc_mod.available()
    if why:
        pytest.skip(why)
    server = orthanc_mod.start(tmp_path_factory.mktemp("orthanc"))
    try:
        yield server
    finally:
        server.stop()


@pytest.fixture(scope="session")
def pacs_series(
    orthanc: orthanc_mod.Orthanc, datasets: Path, tmp_path_factory: pytest.TempPathFactory
) -> dict[str, Series]:
    """The three real series, stored in the Orthanc with their made-up patients."""
    out: dict[str, Series] = {}
    for folder, patient in PATIENTS.items():
        found = read_series(datasets / folder, patient)
        stow(orthanc, found)
        first = found[0]
        out[folder] = Series(
            folder, patient[0], patient[1], patient[3], str(first.StudyInstanceUID),
            str(first.SeriesInstanceUID), str(first.get("FrameOfReferenceUID", "")), len(found),
        )  # fmt: skip
        if folder == ABDOMEN:  # its TotalSegmentator labels as a DICOM SEG beside it
            import pydicom

            from pacs.dicom_data import write_seg

            seg = pydicom.dcmread(write_seg(tmp_path_factory.mktemp("seg"), datasets, found))
            stow(orthanc, [seg])
            out[folder].segmentation = str(seg.SeriesInstanceUID)
    return out
