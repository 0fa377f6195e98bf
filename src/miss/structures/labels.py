"""Label names and colours: colour-table files, NIfTI label tables, TotalSegmentator.

Where a label map's names come from, first match wins (:func:`find_label_table`):

1. a colour-table file beside it: ``<stem>.ctbl``, ``<stem>.txt``,
   ``<stem>_ColorTable.ctbl`` or ``<stem>_ColorTable.txt`` (``stem`` without
   ``.nii.gz``/``.mhd``/...), else the folder's only ``.ctbl`` file (3D Slicer
   names that file after the colour node, not after the volume);
2. a label table inside a NIfTI header (the CaretExtension ``LabelTable`` that
   TotalSegmentator and Connectome Workbench write);
3. nothing: names ``label N`` and colours from :data:`PALETTE`.

The TotalSegmentator list is used when asked for by name (``"totalseg"``), for
maps that lost their header table. Colour-table formats read: 3D Slicer
(``index name r g b a``, 0-255) and ITK-SNAP (``index r g b alpha vis mesh "name"``).
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import cast

from miss.errors import BadParameter, UnreadableVolume
from miss.structures.labels_totalseg import TOTALSEG_TOTAL

RGB = tuple[float, float, float]

# Paul Tol's "muted" and "light" qualitative schemes: distinguishable for colour-blind
# viewers and pleasant on both a dark and a light background.
_HEX = (
    "CC6677", "88CCEE", "DDCC77", "117733", "AA4499", "44AA99", "999933", "882255",
    "332288", "EE8866", "77AADD", "EEDD88", "FFAABB", "99DDFF", "44BB99", "BBCC33",
)  # fmt: skip
PALETTE: tuple[RGB, ...] = tuple(
    (int(h[0:2], 16) / 255, int(h[2:4], 16) / 255, int(h[4:6], 16) / 255) for h in _HEX
)

# 3D Slicer's generic-anatomy colours (sRGB 0-255 / 255) for threshold structures.
SKIN: RGB = (177 / 255, 122 / 255, 101 / 255)
BONE: RGB = (241 / 255, 214 / 255, 145 / 255)
SOFT_TISSUE: RGB = (216 / 255, 101 / 255, 79 / 255)

_STEM_SUFFIXES = (".nii.gz", ".seg.nrrd", ".nii", ".nrrd", ".nhdr", ".mhd", ".mha", ".gz")
_TABLE_SUFFIXES = (".ctbl", ".txt", "_ColorTable.ctbl", "_ColorTable.txt")


@dataclass(frozen=True)
class LabelInfo:
    """Name, sRGB colour (fractions, or None for the palette) and opacity of one label."""

    name: str
    color: RGB | None = None
    opacity: float = 1.0


LabelTable = dict[int, LabelInfo]
TableSpec = str | os.PathLike[str] | Mapping[int, LabelInfo | str] | None


def default_color(label: int) -> RGB:
    """The palette colour of a label: stable per id, so label 5 looks alike in every scene."""
    return PALETTE[(int(label) - 1) % len(PALETTE)]


def describe(label: int, table: Mapping[int, LabelInfo] | None) -> LabelInfo:
    """The table's entry for ``label`` with gaps filled: ``label N``, palette colour."""
    info = (table or {}).get(int(label))
    if info is None:
        return LabelInfo(f"label {label}", default_color(label))
    return LabelInfo(info.name, info.color or default_color(label), info.opacity)


def parse_color_table(text: str, source: str = "colour table") -> LabelTable:
    """Parse a 3D Slicer or ITK-SNAP colour table.

    Parameters
    ----------
    text : str
        The file's text; ``#`` starts a comment.
    source : str
        Named in error messages.

    Returns
    -------
    dict of int to LabelInfo
        Colours as sRGB fractions; opacity 1 where the file says 0 (Slicer's
        background row) so that a listed structure is never invisible.
    """
    table: LabelTable = {}
    for number, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if '"' not in line:  # a quoted ITK-SNAP name may itself hold a '#'
            line = line.split("#", 1)[0].strip()
        if not line or line.startswith("#"):
            continue
        try:
            label, info = _itksnap_row(line) if '"' in line else _slicer_row(line)
        except (ValueError, IndexError):
            raise UnreadableVolume(
                f"{source}, line {number}: expected 'index name r g b a' (3D Slicer) or "
                f"'index r g b alpha vis mesh \"name\"' (ITK-SNAP), got {line[:60]!r}."
            ) from None
        table[label] = info
    return table


def _slicer_row(line: str) -> tuple[int, LabelInfo]:
    """``index name r g b [a]``, colours 0-255; a name with spaces is tolerated."""
    fields = line.split()
    has_alpha = len(fields) >= 6 and all(f.isdigit() for f in fields[-4:])
    numbers = fields[-4:] if has_alpha else fields[-3:]
    name = " ".join(fields[1 : len(fields) - len(numbers)])
    if not name:
        raise ValueError("no name")
    rgba = [int(x) / 255 for x in numbers]
    opacity = rgba[3] if has_alpha and rgba[3] > 0 else 1.0
    return int(fields[0]), LabelInfo(name, (rgba[0], rgba[1], rgba[2]), opacity)


def _itksnap_row(line: str) -> tuple[int, LabelInfo]:
    """``index r g b alpha visible mesh "name"``: colours 0-255, alpha a fraction."""
    head, name = line.split('"', 1)
    fields = head.split()
    r, g, b = (int(x) / 255 for x in fields[1:4])
    alpha = float(fields[4])
    return int(fields[0]), LabelInfo(name.rsplit('"', 1)[0], (r, g, b), alpha if alpha > 0 else 1.0)


def read_color_table(path: str | os.PathLike[str]) -> LabelTable:
    """Read a colour-table file (see :func:`parse_color_table`)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8", errors="replace")
    except OSError as exc:
        raise UnreadableVolume(f"{p}: cannot read the colour table ({exc.strerror}).") from exc
    return parse_color_table(text, p.name)


def nifti_label_table(path: str | os.PathLike[str]) -> LabelTable | None:
    """The CaretExtension ``LabelTable`` in a NIfTI header, or None when there is none."""
    name = str(path).lower()
    if not name.endswith((".nii", ".nii.gz")) or not _has_extensions(Path(path)):
        return None
    import nibabel as nib  # 0.3 s to load: for NIfTI files with header extensions only

    try:
        # a .nii file: a NIfTI image, whose header has extensions
        extensions = cast("nib.Nifti1Image", nib.load(path)).header.extensions
    except Exception:  # a damaged header is the reader's to diagnose, not ours
        return None
    for extension in extensions:
        content = extension.get_content()
        if isinstance(content, bytes) and b"<LabelTable" in content:
            return _caret_table(content)
    return None


def _has_extensions(path: Path) -> bool:
    """The NIfTI-1/2 header's extension flag (byte 348 or 540) is set; True when unsure."""
    from miss.io.nifti_header import NIFTI2_MAGICS, TRUNCATION_ERRORS, open_stream

    try:
        with open_stream(path) as stream:
            head = stream.read(544)
    except (*TRUNCATION_ERRORS, OSError):
        return True  # let nibabel try, and fail with its own message
    at = 540 if head[4:8] in NIFTI2_MAGICS else 348
    return len(head) <= at or head[at] != 0


def _caret_table(xml: bytes) -> LabelTable | None:
    """Parse ``<Label Key=.. Red=.. Green=.. Blue=.. Alpha=..>name</Label>`` (fractions)."""
    import xml.etree.ElementTree as ET  # here: ``miss info`` on a plain scan needs none

    try:
        root = ET.fromstring(xml.decode("utf-8", "replace").strip().strip("\0"))
    except ET.ParseError:
        return None
    table: LabelTable = {}
    for item in root.iter("Label"):
        rgb = tuple(min(max(float(item.get(c, "0.8")), 0.0), 1.0) for c in ("Red", "Green", "Blue"))
        alpha = float(item.get("Alpha", "1"))
        table[int(item.get("Key", "0"))] = LabelInfo(
            (item.text or "").strip() or f"label {item.get('Key')}",
            (rgb[0], rgb[1], rgb[2]),
            alpha if 0 < alpha <= 1 else 1.0,
        )
    return table or None


def totalsegmentator_table() -> LabelTable:
    """TotalSegmentator ``total`` (v2) names with colours by kind of structure."""
    return {
        label: LabelInfo(name, _totalseg_color(label, name))
        for label, name in TOTALSEG_TOTAL.items()
    }


_KINDS: tuple[tuple[str, RGB], ...] = (
    (r"vertebrae|rib_|sacrum|hip_|femur|humerus|scapula|clavicula|skull|sternum", BONE),
    (r"costal_cartilage", (0.83, 0.87, 0.80)),
    (r"aorta|artery|trunk", (0.85, 0.25, 0.22)),
    (r"vein|vena", (0.25, 0.40, 0.80)),
    (r"gluteus|autochthon|iliopsoas", (0.75, 0.40, 0.35)),
    (r"lung", (0.95, 0.75, 0.75)),
    (r"liver", (0.62, 0.27, 0.22)),
    (r"spleen", (0.62, 0.30, 0.42)),
    (r"kidney|adrenal", (0.76, 0.45, 0.35)),
    (r"heart|atrial", (0.80, 0.30, 0.30)),
    (r"stomach|bowel|colon|duodenum|esophagus|gallbladder|pancreas", (0.93, 0.72, 0.55)),
    (r"brain|spinal_cord", (0.96, 0.87, 0.72)),
)


def _totalseg_color(label: int, name: str) -> RGB:
    for pattern, color in _KINDS:
        if re.search(pattern, name):
            return color
    return default_color(label)


def table_path(volume_path: str | os.PathLike[str]) -> Path | None:
    """The colour-table file beside a label map, by the rules in the module docstring."""
    p = Path(volume_path)
    if p.is_dir():
        return None
    stem = p.name
    for suffix in _STEM_SUFFIXES:
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
            break
    for suffix in _TABLE_SUFFIXES:
        candidate = p.with_name(stem + suffix)
        if candidate.is_file() and candidate != p:
            return candidate
    tables = sorted(p.parent.glob("*.ctbl"))
    return tables[0] if len(tables) == 1 else None


def find_label_table(volume_path: str | os.PathLike[str]) -> tuple[LabelTable, str] | None:
    """The label table that comes with a label-map file, and where it was found."""
    beside = table_path(volume_path)
    if beside is not None:
        return read_color_table(beside), str(beside.name)
    embedded = nifti_label_table(volume_path)
    if not embedded:
        return None
    totalseg = totalsegmentator_table()
    if all(totalseg.get(k, LabelInfo("")).name == v.name for k, v in embedded.items()):
        # TotalSegmentator writes a cycle of 8 primaries; its names deserve anatomical colours.
        return {k: totalseg[k] for k in embedded}, "NIfTI header label table (TotalSegmentator)"
    return embedded, "NIfTI header label table"


def resolve_table(
    spec: TableSpec, volume_path: str | os.PathLike[str] | None = None
) -> LabelTable | None:
    """A label table from what the user gave.

    Parameters
    ----------
    spec : None, "auto", "none", "totalseg", a file path, or a mapping
        None or ``"auto"`` looks beside ``volume_path`` (:func:`find_label_table`);
        a path is a colour table, or a NIfTI label map whose own table to use;
        a mapping may give names (str) or :class:`LabelInfo` per label.
    volume_path : path, optional
        The label map's file, for ``"auto"``.
    """
    if isinstance(spec, Mapping):
        return {
            int(k): v if isinstance(v, LabelInfo) else LabelInfo(str(v)) for k, v in spec.items()
        }
    text = None if spec is None else os.fspath(spec)
    if text is None or text == "auto":
        found = find_label_table(volume_path) if volume_path is not None else None
        return found[0] if found else None
    if text == "none":
        return None
    if text.lower() in ("totalseg", "totalsegmentator"):
        return totalsegmentator_table()
    if not Path(text).is_file():
        raise BadParameter(
            f"label table {text!r} is neither a file nor one of auto, none, totalseg; "
            "give a 3D Slicer .ctbl/.txt or ITK-SNAP label file."
        )
    if text.lower().endswith((".nii", ".nii.gz")):  # a label map: the table it comes with
        found = find_label_table(text)
        return found[0] if found else None
    return read_color_table(text)
