"""A reader's diagnosis said plainly for the person who uploaded the file.

Readers write for whoever debugs a file ("notes.nii.gz: not a NIfTI file: no 'n+1'
magic at byte 344 (found b'ohel'); check it was not renamed ..."). The upload's answer
keeps that as ``technical`` and gives as ``detail`` one sentence without byte offsets,
magic numbers or header fields, naming the file once: "notes.nii.gz: not a NIfTI file;
check it was not renamed from another format or damaged."
"""

from __future__ import annotations

import re
from collections.abc import Sequence

from miss.errors import MissError, UnreadableVolume, UnsafeArchive, UnsupportedFormat

#: What marks a phrase as the technical detail: byte positions, magic numbers, raw
#: bytes, hexadecimal values, DICOM tags.
TECHNICAL = re.compile(
    r"\bbytes? \d|\bat byte\b|\bmagic\b|\boffset\b|\b0x[0-9a-fA-F]|\bb'|\bb\"|"
    r"\([0-9A-Fa-f]{4},[0-9A-Fa-f]{4}\)"
)
#: A file name a reader put before its diagnosis ("IM0005: ", "ct/01.dcm: ").
_NAME = re.compile(r"^[^\s:]+: ")


def _parentheticals(text: str) -> list[tuple[int, int]]:
    """(start, end) of each outermost parenthesised phrase, nesting respected."""
    spans, depth, start = [], 0, 0
    for i, char in enumerate(text):
        if char == "(":
            start = i if depth == 0 else start
            depth += 1
        elif char == ")" and depth:
            depth -= 1
            if depth == 0:
                spans.append((start, i + 1))
    return spans


def _without_technical_asides(text: str) -> str:
    """``text`` without the parenthesised phrases that hold technical detail."""
    for start, end in reversed(_parentheticals(text)):
        if TECHNICAL.search(text[start:end]):
            text = text[:start].rstrip() + text[end:]
    return text


def plain_message(message: str, label: str) -> str:
    """One sentence for a person: ``label`` (the file's name) once, the diagnosis without
    its technical clauses, and the fix the reader named."""
    text = _without_technical_asides(message.strip())
    while _NAME.match(text):
        text = _NAME.sub("", text, count=1)
    diagnosis, _, fix = text.partition("; ")
    clauses = diagnosis.split(": ")
    kept = [clauses[0], *(c for c in clauses[1:] if not TECHNICAL.search(c))]
    said = ": ".join(kept).rstrip(". ")
    return f"{label}: {said}; {fix}" if fix else f"{label}: {said}."


def explained(exc: MissError, label: str) -> MissError:
    """``exc`` as the upload answers it: a reader's diagnosis (a file it could not read)
    as :func:`plain_message` with the original as ``technical``; anything else (limits,
    unsafe archives, a series to choose) as it is, being plain already."""
    if isinstance(exc, UnsafeArchive) or not isinstance(exc, UnreadableVolume | UnsupportedFormat):
        return exc
    plain = plain_message(str(exc), label)
    if plain == str(exc):
        return exc
    said = type(exc)(plain)
    said.technical = str(exc)  # type: ignore[union-attr]  # read by the error handler
    return said


#: A reader's note on what it changed, and the same said for a physician: the gantry tilt
#: and the uneven slice gaps of issue 42 ("the affine is sheared", "linear interpolation",
#: "the median gap (the smallest would exceed 4x)" mean nothing to them).
_NOTES_SAID_PLAINLY = (
    (
        re.compile(r"^gantry tilt: slices step ([\d.]+) deg off their normal\b.*"),
        r"The scanner's gantry was tilted \1°: each slice was placed at its true slant, its pixels "
        "unchanged",
    ),
    (
        re.compile(
            r"^uneven slice gaps \(([\d.]+)-([\d.]+) mm\): resampled (\d+) slices onto (\d+) "
            r"slices ([\d.]+) mm apart\b.*"
        ),
        r"The gaps between slices were uneven (\1 to \2 mm): the \3 slices were blended "
        r"into \4 evenly spaced slices, \5 mm apart",
    ),
    (
        re.compile(r"^no usable PixelSpacing: assumed 1 mm pixels$"),
        "The scan did not say its pixel size: 1 mm pixels were assumed",
    ),
    (
        re.compile(
            r"^(?:`space directions` without `space`|no `space` field|space '.*' has no "
            r"anatomical orientation): axes taken as LPS.*"
        ),
        "The file did not say which way the patient lies: the usual orientation (LPS) was assumed",
    ),
    (
        re.compile(r"^no usable `spacings`: 1 mm assumed where missing$"),
        "The file did not give every voxel size: 1 mm was assumed where missing",
    ),
    (
        re.compile(r"^the header mixed `space` with `spacings`.*"),
        "The file gave its orientation in two ways: its voxel sizes were read along the "
        "scan's axes",
    ),
    (re.compile(r"^contours rasterised$"), "The outlined structures were filled in as voxels"),
    (
        re.compile(r"^(?:pydicom|nibabel): (.+)"),
        r"An odd entry in the file's header was passed over (\1)",
    ),
)


def plain_notes(notes: Sequence[str]) -> list[str]:
    """A volume's notes (what its reader changed or assumed) as a page shows them: the
    known technical ones reworded, the others without technical asides (byte offsets,
    tags) and each starting with a capital."""
    said = []
    for note in notes:
        for pattern, plain in _NOTES_SAID_PLAINLY:
            if pattern.match(note):
                note = pattern.sub(plain, note, count=1)
                break
        note = _without_technical_asides(note.strip())
        said.append(note[:1].upper() + note[1:])
    return said
