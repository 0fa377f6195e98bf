"""De-identification in the spirit of the DICOM PS3.15 Basic Application Level
Confidentiality Profile, applied to a ``Volume`` before anything of it is stored.

What the profile asks and what MISS does with it:

- Patient, physician, institution, accession and date attributes (``IDENTIFYING``): the
  readers put them in ``volume.patient``, never in ``volume.meta``; they leave here as a
  separate identity record that the server keeps for the owner only.
- UIDs (study, series, frame of reference): replaced by ``2.25.<128-bit integer>`` from
  an HMAC of the original under a server key: the same original gives the same new UID on
  every upload to that server (series stay recognisable as the same), and without the
  key nobody can go back or test a guess.
- Descriptors (series description, reader notes): the "clean descriptors" option -- any
  identity value found in them is cut out.
- Private tags: never read into a ``Volume``; only their count is reported.
- Burned-in annotation (``BurnedInAnnotation == YES``): pixels cannot be cleaned here, so
  the flag is carried on the volume for the pages to warn about.
"""

from __future__ import annotations

import hashlib
import hmac
import re
from dataclasses import dataclass, replace
from typing import Any

from miss.types import Volume

#: DICOM keywords the basic profile removes or replaces that a slice header may carry.
IDENTIFYING: tuple[str, ...] = (
    "PatientName",
    "PatientID",
    "IssuerOfPatientID",
    "OtherPatientIDs",
    "OtherPatientNames",
    "PatientBirthDate",
    "PatientBirthTime",
    "PatientBirthName",
    "PatientMotherBirthName",
    "PatientSex",
    "PatientAge",
    "PatientAddress",
    "PatientTelephoneNumbers",
    "MilitaryRank",
    "BranchOfService",
    "MedicalRecordLocator",
    "EthnicGroup",
    "Occupation",
    "AdditionalPatientHistory",
    "PatientComments",
    "CountryOfResidence",
    "RegionOfResidence",
    "InstitutionName",
    "InstitutionAddress",
    "InstitutionalDepartmentName",
    "StationName",
    "DeviceSerialNumber",
    "ReferringPhysicianName",
    "ReferringPhysicianAddress",
    "ReferringPhysicianTelephoneNumbers",
    "PhysiciansOfRecord",
    "PerformingPhysicianName",
    "NameOfPhysiciansReadingStudy",
    "OperatorsName",
    "RequestingPhysician",
    "AccessionNumber",
    "StudyID",
    "RequestedProcedureID",
    "AdmissionID",
    "StudyDescription",
    "StudyDate",
    "StudyTime",
    "SeriesDate",
    "SeriesTime",
    "AcquisitionDate",
    "AcquisitionDateTime",
    "ContentDate",
    "ContentTime",
)
#: Person-name attributes: their parts (family, given ...) are cut out one by one, since a
#: description may spell "John Doe" where the header says "DOE^JOHN".
PERSON_NAMES = frozenset(
    {
        "PatientName",
        "OtherPatientNames",
        "PatientBirthName",
        "PatientMotherBirthName",
        "ReferringPhysicianName",
        "PhysiciansOfRecord",
        "PerformingPhysicianName",
        "NameOfPhysiciansReadingStudy",
        "OperatorsName",
        "RequestingPhysician",
    }
)
#: Removed with the rest but not searched for in descriptors: a study description "HEAD"
#: is no identity, and cutting it out of "HEAD 5 mm" only hurts.
NOT_SEARCHED = frozenset({"StudyDescription", "PatientSex", "PatientAge"})
#: ``meta`` keys holding one UID each.
UID_KEYS = ("series_uid", "study_uid", "frame_of_reference")
PROFILE = "DICOM PS3.15 basic application level confidentiality profile (clean descriptors)"
REMOVED = "[removed]"
#: Values shorter than this are not searched for in text (a sex "M", an age "04Y").
MIN_VALUE = 3


def remap_uid(uid: str, key: bytes) -> str:
    """A new UID for ``uid``, stable under ``key``: ``2.25.`` and a 128-bit integer
    (at most 44 characters, within DICOM's 64)."""
    if not uid:
        return ""
    digest = hmac.new(key, uid.encode("ascii", "replace"), hashlib.sha256).digest()
    return f"2.25.{int.from_bytes(digest[:16], 'big')}"


def identity_values(patient: dict[str, Any]) -> list[str]:
    """Every string to cut out of free text: whole values, and the parts of person names;
    longest first, so "Doe^John" goes before "Doe"."""
    values: set[str] = set()
    for keyword, value in patient.items():
        if keyword in NOT_SEARCHED:
            continue
        for item in re.split(r"\\", str(value or "")):
            item = item.strip()
            if len(item) >= MIN_VALUE:
                values.add(item)
                values.add(item.replace("^", " ").strip())
            if keyword in PERSON_NAMES:
                values.update(p for p in re.split(r"[\^\s,=]+", item) if len(p) >= MIN_VALUE)
    return sorted(values, key=lambda v: (-len(v), v))


def scrub(text: str, values: list[str]) -> str:
    """``text`` with every identity value cut out (case-insensitive)."""
    for value in values:
        text = re.sub(re.escape(value), REMOVED, text, flags=re.IGNORECASE)
    return text


def contains_identity(text: str, values: list[str]) -> bool:
    lower = text.lower()
    return any(v.lower() in lower for v in values)


@dataclass(frozen=True)
class Deidentified:
    """A volume fit to store and share, the identity kept apart, and what was done."""

    volume: Volume
    identity: dict[str, Any]
    report: dict[str, Any]


def deidentify(volume: Volume, key: bytes) -> Deidentified:
    """Strip ``volume`` of patient identity (see the module doc); UIDs remapped under ``key``.

    ``identity`` holds the original values (``patient``) and the UID mapping (``uids``:
    original -> new); it is empty for a volume that carried none (NIfTI, the phantom).
    """
    patient = {k: str(v) for k, v in volume.patient.items() if str(v or "").strip()}
    values = identity_values(patient)
    meta = dict(volume.meta)
    uids: dict[str, str] = {}

    def new_uid(uid: Any) -> str:
        uid = str(uid or "")
        if uid:
            uids[uid] = remap_uid(uid, key)
        return uids.get(uid, "")

    for name in UID_KEYS:
        if name in meta:
            meta[name] = new_uid(meta[name])
    meta["series"] = [
        {
            **s,
            "uid": new_uid(s.get("uid")),
            "description": scrub(str(s.get("description", "")), values),
        }
        for s in meta.get("series") or []
    ]
    meta["series_description"] = scrub(str(meta.get("series_description", "")), values)
    meta["notes"] = [scrub(str(n), values) for n in meta.get("notes") or []]
    report = {
        "profile": PROFILE,
        "removed": sorted(patient),
        "uids_remapped": len(uids),
        "private_tags_dropped": int(meta.get("private_tags", 0) or 0),
        "burned_in_annotation": bool(meta.get("burned_in_annotation", False)),
    }
    identity = {"patient": patient, "uids": uids} if patient or uids else {}
    return Deidentified(replace(volume, meta=meta, patient={}), identity, report)
