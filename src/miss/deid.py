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
- Descriptors (series description, body part, reader notes): the "clean descriptors"
  option -- any identity value found in them is cut out, in any case and accents
  ("MÜLLER^JÖRG" as "Mueller Joerg" or "MULLER JORG"), and whatever looks like a person
  name ("Doe^John") or a date goes too, even where the header names nobody.
- Private tags: never read into a ``Volume``; only their count is reported.
- Burned-in annotation (``BurnedInAnnotation == YES``): pixels cannot be cleaned here, so
  the flag is carried on the volume for the pages to warn about.
"""

from __future__ import annotations

import functools
import re
from collections.abc import Callable
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
#: Values shorter than this are cut from text only as whole words ("LI" in "NA_LI_head",
#: never in "SLICE"); longer ones wherever they stand.
MIN_VALUE = 3
#: Attributes holding a DICOM date (YYYYMMDD, or a date-time that starts with one).
DATES = frozenset(
    {"PatientBirthDate", "StudyDate", "SeriesDate", "AcquisitionDate", "AcquisitionDateTime",
     "ContentDate"}
)  # fmt: skip
#: Month names as dates are spelled in English free text.
_MONTHS = (
    "January", "February", "March", "April", "May", "June",
    "July", "August", "September", "October", "November", "December",
)  # fmt: skip


def remap_uid(uid: str, key: bytes) -> str:
    """A new UID for ``uid``, stable under ``key``: ``2.25.`` and a 128-bit integer
    (at most 44 characters, within DICOM's 64)."""
    if not uid:
        return ""
    import hashlib  # here: reading a scan (``miss info``) remaps nothing
    import hmac

    digest = hmac.new(key, uid.encode("ascii", "replace"), hashlib.sha256).digest()
    return f"2.25.{int.from_bytes(digest[:16], 'big')}"


def identity_values(patient: dict[str, Any]) -> list[str]:
    """Every string to cut out of free text: whole values, the parts of person names (in
    either order, joined or not), IDs without their separators, and dates in the usual
    spellings; longest first, so "Doe^John" goes before "Doe"."""
    values: set[str] = set()
    for keyword, value in patient.items():
        if keyword in NOT_SEARCHED:
            continue
        for item in re.split(r"\\", str(value or "")):
            item = item.strip()
            if not item:
                continue
            values.update({item, item.replace("^", " ").strip()})
            if keyword in PERSON_NAMES:
                values.update(_name_spellings(item))
            elif keyword in DATES:
                values.update(date_spellings(item[:8]))
            else:
                values.add(re.sub(r"[^A-Za-z0-9]", "", item))  # "123-45-678" as "12345678"
    values.discard("")
    return sorted(values, key=lambda v: (-len(v), v))


def _name_spellings(name: str) -> set[str]:
    """A person name's parts, and the parts run together in both orders ("LI^NA":
    "LI", "NA", "LINA", "NALI")."""
    parts = [p for p in re.split(r"[\^\s,=]+", name) if p]
    # A double-barrelled name ("Müller-Lüdenscheidt") is also written half.
    found = set(parts) | {p for part in parts for p in part.split("-") if p}
    if len(parts) >= 2:
        found |= {parts[0] + parts[1], parts[1] + parts[0], "".join(parts)}
    return found


def date_spellings(dicom_date: str) -> set[str]:
    """``YYYYMMDD`` as people write it: 1970-03-02, 1970/03/02, 02.03.1970, 2.3.1970,
    03/02/1970, 02-Mar-1970, 2 March 1970, March 2, 1970, 700302 ... (empty for a
    value that is no date)."""
    if not re.fullmatch(r"\d{8}", dicom_date):
        return set()
    y, m, d = dicom_date[:4], dicom_date[4:6], dicom_date[6:]
    if not (1 <= int(m) <= 12 and 1 <= int(d) <= 31):
        return set()
    mi, di, yy = str(int(m)), str(int(d)), y[2:]
    month = _MONTHS[int(m) - 1]
    found = {f"{y}{m}{d}", f"{yy}{m}{d}", f"{d}{m}{y}"}
    for sep in "-/.":
        found |= {f"{y}{sep}{m}{sep}{d}", f"{d}{sep}{m}{sep}{y}", f"{m}{sep}{d}{sep}{y}"}
        found |= {f"{di}{sep}{mi}{sep}{y}", f"{mi}{sep}{di}{sep}{y}", f"{y}{sep}{mi}{sep}{di}"}
        found |= {f"{d}{sep}{m}{sep}{yy}", f"{d}{sep}{month[:3]}{sep}{y}"}
    for name in (month, month[:3]):
        found |= {f"{di} {name} {y}", f"{d} {name} {y}", f"{name} {di}, {y}", f"{name} {di} {y}"}
    return found


#: Letters that Unicode decomposition leaves whole, as people type them without the key.
_LETTERS = {
    "ß": "ss", "ẞ": "SS", "æ": "ae", "Æ": "AE", "ø": "o", "Ø": "O", "œ": "oe", "Œ": "OE",
    "đ": "d", "Đ": "D", "ł": "l", "Ł": "L", "þ": "th", "Þ": "TH", "ı": "i",
}  # fmt: skip
#: The German and Nordic transliterations (Müller as Mueller, Ågård as Aagaard).
_TRANSLITERATED = str.maketrans(
    {"ä": "ae", "ö": "oe", "ü": "ue", "ø": "oe", "å": "aa", "æ": "ae", "ß": "ss"}
)
#: The same spellings undone ("MUELLER" in a header, "Müller" in a description).
_UNDONE = re.compile(r"ae|oe|ue|aa", re.IGNORECASE)
#: A letter or digit of any script: what joins a short value to a word around it.
_WORD = r"[^\W_]"


def _fold_char(char: str) -> str:
    """``char`` without accents (NFKD, combining marks dropped; ø, ß, æ ... spelled out)."""
    if char in _LETTERS:
        return _LETTERS[char]
    import unicodedata  # here: cheap, but only text that is scrubbed needs it

    parts = unicodedata.normalize("NFKD", char)
    return "".join(c for c in parts if not unicodedata.combining(c))


def fold(text: str) -> tuple[str, list[int]]:
    """``text`` without accents, case kept, and for each of its characters the index of
    the character of ``text`` it came from (an "ss" from "ß" points twice to the same)."""
    folded: list[str] = []
    origin: list[int] = []
    for i, char in enumerate(text):
        piece = char if char.isascii() else _fold_char(char)
        folded.append(piece)
        origin.extend([i] * len(piece))
    return "".join(folded), origin


def spellings(value: str) -> set[str]:
    """``value`` as it may be typed: without accents ("Muller"), transliterated
    ("Mueller"), and with transliterations undone ("MUELLER" -> "Muller")."""
    plain = fold(value)[0]
    written = fold(value.lower().translate(_TRANSLITERATED))[0]
    found = {plain, written, _UNDONE.sub(lambda m: m.group()[0], plain)}
    found.add(_UNDONE.sub(lambda m: m.group()[0], written))
    return {v for v in found if v.strip()}


@functools.lru_cache(maxsize=16)
def _matchers(values: tuple[str, ...]) -> tuple[re.Pattern[str], ...]:
    """Regular expressions over folded text for ``values`` (see :func:`scrub`): long
    values anywhere; short ones as words, or as a capitalised piece of a camel-case run."""
    spelled = {s for v in values for s in spellings(v)}
    longest = sorted(spelled, key=lambda v: (-len(v), v))
    long = [re.escape(v) for v in longest if len(v) >= MIN_VALUE]
    short = [re.escape(v) for v in longest if len(v) < MIN_VALUE]
    found = [re.compile("|".join(long), re.IGNORECASE)] if long else []
    if short:
        alts = "|".join(short)
        caps = "|".join(re.escape(v.capitalize()) for v in longest if len(v) < MIN_VALUE)
        found.append(re.compile(rf"(?<!{_WORD})(?:{alts})(?!{_WORD})", re.IGNORECASE))
        found.append(re.compile(rf"(?<=[a-z])(?:{caps})(?![a-z])|(?:{caps})(?=[A-Z][a-z])"))
    return tuple(found)


def scrub(text: str, values: list[str]) -> str:
    """``text`` with every identity value cut out, whatever its case and accents:
    "MÜLLER^JÖRG" goes from "Mueller Joerg", "MULLER JORG" and "Müller" alike (see
    :func:`spellings`). Values shorter than ``MIN_VALUE`` go only where they stand as a
    word of their own (letters and digits around them break no word: "_", "-", ".",
    "^", spaces and case changes do). Matches are found in the folded text and cut from
    the original, whole characters at a time: no "Mü[removed]" is left behind."""
    if not text or not values:
        return text
    folded, origin = fold(text)
    spans = [
        _original_span(text, origin, m.start(), m.end())
        for matcher in _matchers(tuple(values))
        for m in matcher.finditer(folded)
    ]
    return _cut(text, spans)


def _original_span(text: str, origin: list[int], start: int, end: int) -> tuple[int, int]:
    """The span of ``text`` that folded characters ``start:end`` came from, with the
    combining marks that follow it (a decomposed "u" + diaeresis goes whole)."""
    first, last = origin[start], origin[end - 1] + 1
    while last < len(text) and not _fold_char(text[last]):
        last += 1
    return first, last


def _cut(text: str, spans: list[tuple[int, int]]) -> str:
    """``text`` with each run of overlapping or touching ``spans`` replaced by REMOVED."""
    out: list[str] = []
    at = 0
    for start, end in sorted(spans):
        if start > at or not out:
            out.append(text[at:start])
            out.append(REMOVED)
        at = max(at, end)
    return "".join(out) + text[at:]


#: A letter of any script (Müller, Jörg, Łukasz).
_LETTER = r"[^\W\d_]"
#: Free-text patterns that say "a person" or "a date" with nothing known to match: DICOM
#: person names (Doe^John, Müller^Jörg), "Name: ...", "Patient ...", and dates in the
#: usual spellings.
_PATTERNS = [
    re.compile(rf"{_LETTER}(?:{_LETTER}|['\-])*\^(?:{_LETTER}|['\-^ ])*{_LETTER}"),
    re.compile(r"(?i)\b(?:patient(?:'s)?(?:\s+name)?|name|pt)\s*[:=]\s*[^,;\n]+"),
    re.compile(r"(?<!\d)(?:19|20)\d\d[-/.]?(?:0[1-9]|1[0-2])[-/.]?(?:0[1-9]|[12]\d|3[01])(?!\d)"),
    re.compile(r"(?<!\d)(?:0?[1-9]|[12]\d|3[01])[-/.](?:0?[1-9]|1[0-2])[-/.](?:19|20)\d\d(?!\d)"),
    re.compile(r"(?<!\d)(?:0?[1-9]|1[0-2])[-/.](?:0?[1-9]|[12]\d|3[01])[-/.](?:19|20)\d\d(?!\d)"),
    re.compile(
        r"(?i)\b(?:\d{1,2}[ -])?(?:jan|feb|mar|apr|may|jun|jul|aug|sep|sept|oct|nov|dec)[a-z]*\.?"
        r"(?:[ -]\d{1,2},?)?[ -](?:19|20)\d\d\b"
    ),
]


def scrub_patterns(text: str) -> str:
    """``text`` without what looks like a person's name or a date: for every descriptor,
    since a header may give no identity to match (NIfTI, NRRD, MetaImage; a DICOM series
    with an empty PatientName)."""
    for pattern in _PATTERNS:
        text = pattern.sub(REMOVED, text)
    return text


def _cleaner(values: list[str]) -> Callable[[Any], str]:
    def clean(text: Any) -> str:
        return scrub_patterns(scrub(str(text or ""), values))

    return clean


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
    # Formats without identity fields (NIfTI descrip, NRRD content ...), and DICOM headers
    # whose PatientName is empty, still carry what people type: names and dates go by
    # pattern too.
    clean = _cleaner(values)
    meta["series"] = [
        {**s, "uid": new_uid(s.get("uid")), "description": clean(s.get("description", ""))}
        for s in meta.get("series") or []
    ]
    meta["series_description"] = clean(meta.get("series_description", ""))
    if "body_part" in meta:
        meta["body_part"] = clean(meta["body_part"])
    meta["notes"] = [clean(n) for n in meta.get("notes") or []]
    report = {
        "profile": PROFILE,
        "removed": sorted(patient),
        "uids_remapped": len(uids),
        "private_tags_dropped": int(meta.get("private_tags", 0) or 0),
        "burned_in_annotation": bool(meta.get("burned_in_annotation", False)),
    }
    identity = {"patient": patient, "uids": uids} if patient or uids else {}
    return Deidentified(replace(volume, meta=meta, patient={}), identity, report)
