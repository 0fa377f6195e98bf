"""A job, declared once: :class:`JobSpec` and its small typed parts.

- ``source``: where the volume comes from (:class:`FileSource` here; the server's
  uploaded volumes in :mod:`miss.server.jobs`; a PACS series next);
- ``region``: :class:`Region`, sample rate, slice range and voxel box, with the one
  check and the one crop that apply them;
- ``structures``: :class:`Structures`, the parts to build, each a threshold (``level``)
  or label-map labels with its name, colour, opacity, components and smoothing;
- ``decimation``: :class:`Decimation`;
- ``outputs``: :class:`Outputs`, the formats written.

Every field carries its help text and its command-line spelling in ``metadata``; the
REST body (:func:`miss.server.core.schemas.model_request`) and ``miss convert``'s options
(:mod:`miss.cli.options`) are generated from them, so one name, one default and one
check hold in both. The *form* (:meth:`JobSpec.from_dict` / :meth:`JobSpec.to_dict`)
is the 1998 web form, one flat name per field: what the REST API takes and the
database keeps.
"""

from __future__ import annotations

import json
import math
import numbers
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import MISSING, Field, dataclass, field, fields, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from miss.decimate import (
    ERROR_BOUND,
    MAX_ERROR,
    METHOD,
    METHODS,
    REDUCE,
    SCHEDULE,
    SCHEDULES,
    check_decimation,
)
from miss.errors import BadParameter

if TYPE_CHECKING:
    from miss.structures.labels import TableSpec
    from miss.types import Volume

RGB = tuple[float, float, float]

#: What ``components`` may be: every piece, the largest, or one part per piece.
COMPONENT_MODES: tuple[str, ...] = ("all", "largest", "split")
#: Output formats (``miss.export.WRITERS`` holds one writer each).
FORMATS: tuple[str, ...] = (
    "wrl", "wrz", "x3d", "glb", "plain.glb", "stl", "ply", "obj", "3mf"
)  # fmt: skip
#: Most thresholds one job may have (each is a whole surface).
MAX_LEVELS = 16
#: The smoothing passband's default: mild (smaller smooths more).
PASSBAND = 0.1
#: Windowed-sinc iterations a label map's parts get when the job leaves ``smooth`` out: label
#: maps come out of surface nets as voxel blocks, threshold surfaces (none) are already
#: interpolated.
LABEL_SMOOTHING = 20


def param(default: Any, help: str, **cli: Any) -> Any:
    """A declared field: its default, its help text (REST description and ``--help``)
    and how the command line spells it (``flag``, ``metavar``, ``text`` parser,
    ``repeat``; ``cli=False`` for fields only the form derives); ``form``: the range the
    web page offers (``{"min": .., "max": ..}``, see :class:`Declared`)."""
    return field(default=default, metadata={"help": help, **cli})


@dataclass(frozen=True)
class Declared:
    """What :func:`param` declares of a field besides its type and default, typed: what
    the REST schema (:mod:`miss.server.schemas`) is made of."""

    #: The help text: the REST description and ``--help``.
    help: str
    #: In the REST body (False: only the command line or the form derives it).
    api: bool
    #: The REST type where it is not the field's own (a colour is sent as text), or None.
    json: Any
    #: The range the web page's input offers, ``{"min": .., "max": ..}`` (either may be
    #: absent): the page's bounds, narrower than the field's check (which the REST API and
    #: the command line apply) where a wider value is allowed but no one picks it by hand.
    form: dict[str, float]


def declared(f: Field[Any]) -> Declared:
    """``f``'s :class:`Declared`."""
    meta = f.metadata
    return Declared(meta["help"], meta.get("api", True), meta.get("json"), meta.get("form", {}))


# ---------------------------------------------------------------- value checks


# numbers' ABCs, not numpy's types: numpy registers its scalars there when it loads, and
# the command line reads a job without loading numpy at all.
def _is_int(x: Any) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


def _is_num(x: Any) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def _whole(name: str, value: Any, low: int) -> None:
    if value is not None and (not _is_int(value) or value < low):
        raise BadParameter(f"{name} must be a whole number >= {low}, got {value!r}.")


def _finite(name: str, value: Any, what: str = "a number") -> float:
    if not _is_num(value) or not math.isfinite(value):
        raise BadParameter(f"{name} must be {what}, got {value!r}.")
    return float(value)


def parse_labels(labels: str | Sequence[int] | int | None) -> str | tuple[int, ...] | None:
    """``None``, ``"all"``, ``"1,4,7"``, ``7`` or ``[1, 4, 7]`` -> None, "all" or sorted ids."""
    if labels is None or labels == "all":
        return labels
    # checked here whatever it is: it comes from a user
    given: Any = labels
    if _is_int(given):
        given = [int(given)]
    try:
        if isinstance(given, str):
            ids = [int(p) for p in given.split(",")]
        else:
            ids = [int(p) for p in given if not isinstance(p, bool | float)]
            if len(ids) != len(given):
                raise ValueError
    except (TypeError, ValueError):
        raise BadParameter(
            f"labels must be 'all' or label numbers such as 1,4,7; got {given!r}."
        ) from None
    if not ids or min(ids) < 1:
        raise BadParameter(
            f"label numbers are whole numbers >= 1 (0 is background); got {given!r}."
        )
    return tuple(sorted(set(ids)))


def parse_color(value: str | Sequence[float] | None) -> RGB | None:
    """``"#rrggbb"`` or three sRGB fractions -> (r, g, b) fractions; None stays None."""
    if value is None:
        return None
    if isinstance(value, str):
        text = value.strip().removeprefix("#")
        if len(text) == 6 and all(c in "0123456789abcdefABCDEF" for c in text):
            return (int(text[0:2], 16) / 255, int(text[2:4], 16) / 255, int(text[4:6], 16) / 255)
    elif len(value) == 3 and all(_is_num(c) and 0.0 <= c <= 1.0 for c in value):
        return (float(value[0]), float(value[1]), float(value[2]))
    raise BadParameter(f"colour must be '#rrggbb' or three fractions in [0, 1], got {value!r}.")


def color_text(color: RGB) -> str:
    """(r, g, b) fractions -> ``"#rrggbb"``, the form's spelling."""
    return "#" + "".join(f"{round(c * 255):02x}" for c in color)


def check_smoothing(iterations: int, passband: float) -> None:
    """Refuse iteration counts and passbands the filter cannot use, with the fix."""
    if not _is_int(iterations) or iterations < 0:
        raise BadParameter(f"smooth must be a whole number of iterations >= 0, got {iterations!r}.")
    if iterations > 500:
        raise BadParameter(f"smooth={iterations} iterations is far beyond useful; use 10 to 50.")
    if not _is_num(passband) or not 0.0 < passband < 2.0:
        raise BadParameter(
            f"passband must be in (0, 2), got {passband!r}; smaller smooths more (0.1 is mild)."
        )


# ---------------------------------------------------------------- the parts


@dataclass(frozen=True)
class Region:
    """Which voxels the job reads: every ``sample_rate``-th of the slice range and box.

    ``start_slice``/``end_slice`` are 1-based and inclusive along the third voxel axis
    (the paper's start and end slice); ``roi`` is a 0-based inclusive voxel box.
    """

    sample_rate: int | tuple[int, int, int] = param(
        1, "keep every n-th voxel (the paper's marching-cube size): n, or x,y,z",
        metavar="N|X,Y,Z", text="ints",
    )  # fmt: skip
    start_slice: int | None = param(
        None, "first slice, 1-based, inclusive", metavar="A", text="int", form={"min": 1}
    )
    end_slice: int | None = param(
        None, "last slice, 1-based, inclusive", metavar="B", text="int", form={"min": 1}
    )
    roi: tuple[int, int, int, int, int, int] | None = param(
        None, "voxel box i0,i1,j0,j1,k0,k1 (0-based, inclusive)",
        metavar="I0,I1,J0,J1,K0,K1", text="ints",
    )  # fmt: skip

    def __post_init__(self) -> None:
        sr: Any = self.sample_rate  # checked here whatever it is: it comes from a user
        if isinstance(sr, list | tuple) and len(sr) == 1:
            sr = sr[0]
        if isinstance(sr, list | tuple):
            sr = tuple(sr)
        object.__setattr__(self, "sample_rate", sr)
        ok = _is_int(sr) or (isinstance(sr, tuple) and len(sr) == 3 and all(map(_is_int, sr)))
        if not ok or min(self.steps) < 1:
            raise BadParameter(f"sample_rate must be an integer >= 1 or three of them, got {sr!r}.")
        for name in ("start_slice", "end_slice"):
            value = getattr(self, name)
            if value is not None and (not _is_int(value) or value < 1):
                raise BadParameter(f"{name} must be a whole number >= 1 (1-based), got {value!r}.")
        if self.start_slice and self.end_slice and self.start_slice > self.end_slice:
            raise BadParameter(
                f"start_slice {self.start_slice} is after end_slice {self.end_slice}; swap them."
            )
        if self.roi is not None:
            roi = tuple(self.roi)
            if len(roi) != 6 or not all(map(_is_int, roi)) or min(roi) < 0:
                raise BadParameter(
                    f"roi needs six voxel indices i0,i1,j0,j1,k0,k1 >= 0, got {self.roi!r}."
                )
            object.__setattr__(self, "roi", roi)

    @property
    def steps(self) -> tuple[int, int, int]:
        """The sample rate along x, y and z."""
        sr = self.sample_rate  # checked: a whole number or three
        return (sr[0], sr[1], sr[2]) if isinstance(sr, tuple) else (sr, sr, sr)

    def slices(self, n_slices: int) -> tuple[int, int] | None:
        """The 1-based inclusive slice range, a missing end filled from ``n_slices``."""
        if self.start_slice is None and self.end_slice is None:
            return None
        return (self.start_slice or 1, self.end_slice or n_slices)

    def box(self, dims: Sequence[int]) -> list[tuple[int, int]]:
        """0-based inclusive (first, last) voxel per axis; refuses a region that leaves
        fewer than 2 samples along an axis, or slices beyond the volume, with the fix."""
        for name in ("start_slice", "end_slice"):
            value = getattr(self, name)
            if value is not None and value > dims[2]:
                raise BadParameter(
                    f"{name} {value} is outside 1..{dims[2]}, beyond the volume's {dims[2]} "
                    f"slices; use 1..{dims[2]}."
                )
        box = [(0, int(d) - 1) for d in dims]
        if self.roi is not None:
            box = [(self.roi[2 * a], self.roi[2 * a + 1]) for a in range(3)]
        slices = self.slices(int(dims[2]))
        if slices is not None:
            box[2] = (max(box[2][0], slices[0] - 1), min(box[2][1], slices[1] - 1))
        for axis, ((lo, hi), step) in enumerate(zip(box, self.steps, strict=True)):
            if (not 0 <= lo < hi < dims[axis] or (hi - lo) // step < 1) and axis == 2 and slices:
                # Said in the slices' own numbering (1-based), as they were given.
                first, last, n = lo + 1, hi + 1, int(dims[2])
                raise BadParameter(
                    f"slices {first}..{last} at sample rate {step} leave fewer than 2 of the "
                    f"volume's slices 1..{n}; a surface needs at least 2: choose an end_slice "
                    f"of at least {first + step}{' or a lower sample rate' if step > 1 else ''}."
                )
            if not 0 <= lo < hi < dims[axis] or (hi - lo) // step < 1:
                raise BadParameter(
                    f"region {lo}..{hi} along {'xyz'[axis]} at sample rate {step} leaves fewer "
                    f"than 2 of its voxels 0..{dims[axis] - 1}; a surface needs at least 2 along "
                    "each axis: widen the region (slices) or lower the sample rate."
                )
        return box

    def apply(self, volume: Volume) -> Volume:
        """The region at the sample rate, positions still in patient mm (the affine is
        shifted and scaled). The whole volume at rate 1 is returned as it is (no copy);
        striding a label map is nearest-neighbour subsampling. A lazy (chunked) volume's
        region is read here, and only the chunks it crosses."""
        import numpy as np

        from miss.types import Volume

        box = self.box(volume.dims)
        whole = box == [(0, d - 1) for d in volume.dims] and self.steps == (1, 1, 1)
        if whole and isinstance(volume.data, np.ndarray):
            return volume
        picked = tuple(slice(lo, hi + 1, s) for (lo, hi), s in zip(box, self.steps, strict=True))
        shift = np.eye(4)
        shift[:3, :3] = np.diag(np.asarray(self.steps, dtype=np.float64))
        shift[:3, 3] = [lo for lo, _ in box]
        if isinstance(volume.data, np.ndarray):
            data = np.asfortranarray(volume.data[picked])
        else:  # on disk (zarr): a lazy view, read block by block by the surface stage
            from miss.types import StridedView

            data = StridedView(volume.data, box, self.steps)
        return Volume(data, volume.affine @ shift, volume.meta, volume.patient)


@dataclass(frozen=True)
class Structure:
    """One structure: a threshold surface (``level``) or label-map ``labels``.

    ``name``, ``color`` and ``opacity`` left out are chosen by MISS (a level's kind in
    HU, a label table's entry); the other fields say how the surface is cleaned up.
    """

    level: float | None = param(
        None, "threshold in the volume's units (HU for CT); voxels above it are inside",
        metavar="LEVEL", text="float",
    )  # fmt: skip
    labels: str | tuple[int, ...] | None = param(
        None, 'label-map labels, one part each: "all" or ids such as 1,4,7',
        metavar="all|1,4,7", text="str",
    )  # fmt: skip
    name: str | None = param(None, "the part's name (default: from its level or label)")
    color: RGB | None = param(None, 'the part\'s colour, "#rrggbb"', json=str)
    opacity: float | None = param(
        None, "the part's opacity, 0 < opacity <= 1 (1 = opaque)", text="float"
    )
    components: str = param(
        "all", "keep every piece, the largest only, or one part per piece (split)",
        choices=COMPONENT_MODES,
    )  # fmt: skip
    min_size_mm3: float = param(
        0.0, "leave out pieces smaller than this volume (mm³)",
        flag=("--min-size-mm3", "--min-size"), metavar="MM3", text="float", form={"min": 0.0},
    )  # fmt: skip
    max_parts: int = param(
        100, "with components split: at most this many parts (largest first)",
        metavar="N", text="int",
    )  # fmt: skip
    smooth: int | None = param(
        None,
        f"windowed-sinc smoothing iterations (default: {LABEL_SMOOTHING} for labels, 0 for levels)",
        metavar="N", text="int",
    )  # fmt: skip
    passband: float = param(
        PASSBAND, "smoothing passband in (0, 2); smaller smooths more", metavar="P", text="float"
    )

    def __post_init__(self) -> None:
        if (self.level is None) == (self.labels is None):
            raise BadParameter(
                "a part needs a 'level' (threshold in the volume's units, e.g. HU) or "
                f"'labels' of a label map, not {'both' if self.level is not None else 'neither'}."
            )
        if self.level is not None:
            level = _finite("level", self.level, "a number in the volume's units")
            object.__setattr__(self, "level", level)
        object.__setattr__(self, "labels", parse_labels(self.labels))
        object.__setattr__(self, "color", parse_color(self.color))
        if self.name is not None and (not isinstance(self.name, str) or not self.name.strip()):
            raise BadParameter(f"a part's name must be some text, got {self.name!r}.")
        if self.opacity is not None and not (_is_num(self.opacity) and 0 < self.opacity <= 1):
            raise BadParameter(f"opacity must be in (0, 1] (1 = opaque), got {self.opacity!r}.")
        styled = self.name is not None or self.color is not None or self.opacity is not None
        if styled and self.labels is not None and (self.labels == "all" or len(self.labels) != 1):
            raise BadParameter(
                "a name, colour or opacity goes with one label; give each label a part of "
                "its own (or leave them to the label table)."
            )
        self._check_cleanup()

    def _check_cleanup(self) -> None:
        if self.components not in COMPONENT_MODES:
            raise BadParameter(
                f"components must be one of {', '.join(COMPONENT_MODES)}, got {self.components!r}."
            )
        if not _is_num(self.min_size_mm3) or not self.min_size_mm3 >= 0:
            raise BadParameter(f"min size must be a volume in mm³ >= 0, got {self.min_size_mm3!r}.")
        _whole("max_parts", self.max_parts, 1)
        check_smoothing(0 if self.smooth is None else self.smooth, self.passband)

    @property
    def cleanup(self) -> tuple[str, float, int, int | None, float]:
        """What label parts built together must share (they share their boundaries)."""
        return (self.components, self.min_size_mm3, self.max_parts, self.smooth, self.passband)

    def form(self) -> dict[str, Any]:
        """The fields that differ from their defaults, colour as ``#rrggbb``."""
        out = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value != f.default:
                out[f.name] = color_text(value) if f.name == "color" else _plain(value)
        return out


#: The fields every part takes from the form when its own entry leaves them out.
CLEANUP: tuple[str, ...] = ("components", "min_size_mm3", "max_parts", "smooth", "passband")


def _shared(name: str) -> Any:
    """The form's field for a cleanup option: the part's declaration, once."""
    declared = Structure.__dataclass_fields__[name]
    return field(default=declared.default, metadata=declared.metadata)


@dataclass(frozen=True)
class Structures:
    """The structures of a job, as the form spells them.

    ``level`` (one threshold), ``levels`` (several: a scene with the lower ones
    translucent) and ``labels`` make one part each (labels: one per label); the
    cleanup fields apply to all of them. ``parts`` spells the parts one by one
    instead of ``level``/``levels`` (each with its own name, colour, opacity and
    cleanup; what an entry leaves out comes from the fields here); ``labels`` still
    adds the label parts. :attr:`items` is the list either way.
    """

    level: float | None = param(
        None, "threshold in the volume's units (HU for CT); several: 'levels' (--level repeated)",
        flag=("--level",), metavar="LEVEL", text="float", repeat="levels",
    )  # fmt: skip
    levels: tuple[float, ...] | None = param(
        None, f"several thresholds, one structure each, e.g. -500,300; at most {MAX_LEVELS}",
        cli=False,  # --level repeated
    )  # fmt: skip
    labels: str | tuple[int, ...] | None = param(
        None, 'label-map labels to build, one part each: "all" or ids such as 1,4,7 (from the '
        "volume's label map, or the volume itself when it is one)",
        metavar="all|1,4,7", text="str",
    )  # fmt: skip
    components: str = _shared("components")
    min_size_mm3: float = _shared("min_size_mm3")
    max_parts: int = _shared("max_parts")
    smooth: int | None = _shared("smooth")
    passband: float = _shared("passband")
    parts: tuple[Structure, ...] | None = param(
        None, "the parts one by one: [{level or labels, name, color, opacity, components, "
        "min_size_mm3, max_parts, smooth, passband}]; fields left out come from the form",
        flag=("--part",), metavar="level=300,name=bone,color=#f1d691", text="part", repeat="parts",
    )  # fmt: skip

    def __post_init__(self) -> None:
        if self.levels is not None:
            levels = tuple(self.levels) if isinstance(self.levels, list | tuple) else None
            if levels is None or not all(_is_num(v) and math.isfinite(v) for v in levels):
                raise BadParameter(
                    f"levels must be numbers in the volume's units, got {self.levels!r}."
                )
            if len(levels) > MAX_LEVELS:
                raise BadParameter(
                    f"{len(levels)} levels is too many; a model takes at most {MAX_LEVELS} "
                    "(each is a whole surface): make several models."
                )
            object.__setattr__(self, "levels", tuple(float(v) for v in levels) or None)
        if self.level is not None:
            level = _finite("level", self.level, "a number in the volume's units")
            object.__setattr__(self, "level", level)
        object.__setattr__(self, "labels", parse_labels(self.labels))
        if self.parts is not None:
            if self.level is not None or self.levels:
                raise BadParameter(
                    "give the thresholds as 'parts' or as 'level'/'levels', not both."
                )
            if isinstance(self.parts, str | Mapping) or not isinstance(self.parts, Sequence):
                raise BadParameter(f"parts must be a list of objects, got {self.parts!r}.")
            object.__setattr__(self, "parts", tuple(self._part(p) for p in self.parts) or None)
        if not self.items:
            raise BadParameter(
                "a job needs a 'level' (threshold in the volume's units, e.g. HU), "
                "'levels' or 'labels'."
            )
        labelled = {p.cleanup for p in self.items if p.labels is not None}
        if len(labelled) > 1:
            raise BadParameter(
                "label parts are built together (neighbours share their boundaries): give them "
                "the same components, min_size_mm3, max_parts, smooth and passband."
            )

    def _part(self, entry: Structure | Mapping[str, Any]) -> Structure:
        if isinstance(entry, Structure):
            return entry
        if not isinstance(entry, Mapping):
            raise BadParameter(f"each part is an object such as {{'level': 300}}, got {entry!r}.")
        names = {f.name for f in fields(Structure)}
        unknown = set(entry) - names
        if unknown:
            raise BadParameter(
                f"unknown part field(s) {sorted(unknown)}; a part takes {sorted(names)}."
            )
        shared = {name: getattr(self, name) for name in CLEANUP}
        return Structure(**{**shared, **entry})

    @property
    def items(self) -> tuple[Structure, ...]:
        """One :class:`Structure` per threshold or label set, in the form's order."""
        shared = {name: getattr(self, name) for name in CLEANUP}
        levels = self.levels or (() if self.level is None else (self.level,))
        out = list(self.parts or [Structure(level=v, **shared) for v in levels])
        if self.labels is not None:
            out.append(Structure(labels=self.labels, **shared))
        return tuple(out)

    @property
    def levels_used(self) -> tuple[float, ...]:
        """Every threshold the job surfaces."""
        return tuple(p.level for p in self.items if p.level is not None)

    @property
    def labels_used(self) -> str | tuple[int, ...] | None:
        """The labels the job builds: None, "all" or the ids of every label part."""
        wanted = [p.labels for p in self.items if p.labels is not None]
        if not wanted:
            return None
        if "all" in wanted:
            return "all"
        # past "all", every part's labels are ids
        return tuple(sorted({i for ids in wanted if not isinstance(ids, str) for i in ids}))


@dataclass(frozen=True)
class Decimation:
    """Fewer triangles within an error bound; bounds are fractions of the bounding-box
    diagonal (the paper's 0.0002 and 0.002). ``guaranteed``: the output stays within the
    bound of the input surface (two-sided, measured), and decimation stops at ``reduce``
    (fraction of triangles removed) or when nothing more can go within the bound;
    ``paper``: the bound is raised up to ``max_error`` until ``reduce`` is met."""

    method: str = param(
        METHOD, '"none", "schroeder" (the paper\'s), "quadric" (fast), "collapse" (fewer '
        'triangles within the bound) or "placed" (the fewest: vertices moved; the slowest)',
        name="decimate", choices=METHODS,
    )  # fmt: skip
    error_bound: float = param(
        ERROR_BOUND, "error bound, fraction of the bounding-box diagonal (paper: 0.0002, 0.002): "
        "the most the model may deviate from the surface, measured (with schedule 'paper', "
        "the first bound); 0.002 is 0.7 mm on a head CT, under a voxel",
        metavar="E", text="float", form={"min": 0.00001, "max": 0.01},
    )  # fmt: skip
    reduce: float = param(
        REDUCE, "target fraction of triangles removed, 0 <= reduce < 1",
        metavar="R", text="float", form={"min": 0.0, "max": 0.99},
    )  # fmt: skip
    max_error: float = param(
        MAX_ERROR, "schedule 'paper' only: the bound is raised until reduce is met, never past "
        "this fraction of the diagonal",
        metavar="E", text="float",
    )  # fmt: skip
    schedule: str = param(
        SCHEDULE, '"guaranteed" (the bound is a cap, measured to hold) or "paper" '
        "(the 1998 schedule: the bound raised up to max_error until reduce is met; the report "
        "gives the bound it ended at, also measured to hold)",
        choices=SCHEDULES,
    )  # fmt: skip

    def __post_init__(self) -> None:
        check_decimation(self.method, self.error_bound, self.reduce, self.max_error, self.schedule)


@dataclass(frozen=True)
class Outputs:
    """The formats written. The server writes every one; ``miss convert`` the ones its
    ``-o`` files name by their extensions."""

    formats: tuple[str, ...] = param(("glb",), "output formats", cli=False, api=False)

    def __post_init__(self) -> None:
        if isinstance(self.formats, str) or not isinstance(self.formats, Sequence):
            raise BadParameter(f"formats must be a list such as ['glb'], got {self.formats!r}.")
        keys = tuple(dict.fromkeys(str(f).lower().lstrip(".") for f in self.formats))
        bad = [f for f in keys if f not in FORMATS]
        if bad or not keys:
            raise BadParameter(f"unknown output format(s) {bad}; choose from {', '.join(FORMATS)}.")
        object.__setattr__(self, "formats", keys)


# ---------------------------------------------------------------- where the volume comes from


@dataclass(frozen=True)
class Loaded:
    """What a source gives a job: the volume, a label map laid over it (or None), the
    table that names its labels, and a title for the model."""

    volume: Volume
    label_map: Volume | None = None
    table: TableSpec = None
    title: str | None = None
    provenance: dict[str, str] = field(default_factory=dict)


class Source(Protocol):
    """Where a job's volume comes from: ``load()`` once, in the process that runs it."""

    def load(self, labels: bool) -> Loaded:
        """The volume; with ``labels`` the label map and table a labels job reads."""
        ...


@dataclass(frozen=True)
class FileSource:
    """A volume file or DICOM folder on this machine (``miss convert``'s PATH)."""

    path: str = field(
        metadata={"help": "a DICOM folder or .zip, .nii(.gz), .nrrd/.nhdr, .mha/.mhd"}
    )
    series: str | None = param(None, "DICOM SeriesInstanceUID when the folder holds several")
    label_map: str | None = param(
        None, "a label map of the volume (e.g. TotalSegmentator output), laid over it in mm",
        metavar="SEG",
    )  # fmt: skip
    label_table: str = param(
        "auto", "label names and colours: a 3D Slicer .ctbl/.txt or ITK-SNAP file; auto looks "
        "beside the label map and in its NIfTI header",
        metavar="auto|none|totalseg|FILE",
    )  # fmt: skip

    def load(self, labels: bool) -> Loaded:
        """Read the volume file (to a chunked array on disk, read lazily, when its voxels
        exceed the memory budget: :func:`miss.io.bounded.load_within`); with ``labels``,
        its label map and label table too."""
        from miss.io import load_volume
        from miss.io.bounded import load_within
        from miss.structures.labels import resolve_table

        volume = load_within(self.path, series=self.series)
        if not labels:
            return Loaded(volume, title=Path(self.path).name)
        label_map = load_volume(self.label_map) if self.label_map else None
        table = resolve_table(self.label_table, self.label_map or self.path)
        return Loaded(volume, label_map, table, Path(self.path).name)


# ---------------------------------------------------------------- the job


#: The groups of the form, in order: (JobSpec attribute, class).
GROUPS: tuple[tuple[str, type], ...] = (
    ("region", Region),
    ("structures", Structures),
    ("decimation", Decimation),
    ("outputs", Outputs),
)


def form_name(f: Field[Any]) -> str:
    """A field's name in the form (REST body, CLI option, database)."""
    return f.metadata.get("name", f.name)


def form_fields() -> Iterator[tuple[str, type, Field[Any]]]:
    """(group attribute, group class, field) of every field of the form, in order."""
    for attr, cls in GROUPS:
        for f in fields(cls):
            yield attr, cls, f


def default_of(f: Field[Any]) -> Any:
    """A dataclass field's default, None when it has none."""
    return None if f.default is MISSING else f.default


@dataclass(frozen=True)
class JobSpec:
    """One job: where from, which voxels, which structures, how decimated, which files.

    Built from the form with :meth:`from_dict` (or :meth:`of` for keyword arguments);
    every part validates itself, so a JobSpec that exists is a job that can run.
    """

    structures: Structures
    region: Region = field(default_factory=Region)
    decimation: Decimation = field(default_factory=Decimation)
    outputs: Outputs = field(default_factory=Outputs)
    source: Source | None = field(default=None, compare=False)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], source: Source | None = None) -> JobSpec:
        """From the form (JSON-like); unknown names and bad values raise ``BadParameter``."""
        if not isinstance(data, Mapping):
            raise BadParameter(f"a job is an object of parameters, got {type(data).__name__}.")
        known = {form_name(f): (attr, f.name) for attr, _, f in form_fields()}
        unknown = set(data) - set(known)
        if unknown:
            raise BadParameter(
                f"unknown job parameter(s) {sorted(unknown)}; known: {sorted(known)}."
            )
        groups: dict[str, dict[str, Any]] = {attr: {} for attr, _ in GROUPS}
        for key, value in data.items():
            attr, name = known[key]
            groups[attr][name] = tuple(value) if isinstance(value, list) else value
        try:
            built = {attr: cls_(**groups[attr]) for attr, cls_ in GROUPS}
        except TypeError as exc:  # a value of a type no check expected
            raise BadParameter(f"bad job parameters: {exc}.") from None
        return cls(**built, source=source)

    @classmethod
    def of(cls, source: Source | None = None, **form: Any) -> JobSpec:
        """``JobSpec.of(level=300, sample_rate=2, formats=("glb",))``: the form as keywords."""
        return cls.from_dict(form, source)

    def to_dict(self) -> dict[str, Any]:
        """The form: every field by its form name; ``parts`` as plain objects."""
        out: dict[str, Any] = {}
        for attr, _, f in form_fields():
            value = getattr(getattr(self, attr), f.name)
            if f.name == "parts" and value is not None:
                value = [p.form() for p in value]
            out[form_name(f)] = _plain(value)
        return out

    def key(self) -> str:
        """Stable hash of what shapes the model (not the formats, not the source).

        The structure fields at their defaults are left out, so the jobs of one level
        made before scenes existed keep their keys, and with them their stored models; so is
        the schedule "paper" (what every model made before bounds were held used), while
        "guaranteed", the default now, makes new models.
        """
        d = self.to_dict()
        d.pop("formats")
        if d.get("schedule") == "paper":
            del d["schedule"]
        d["sample_rate"] = list(self.region.steps)
        for name in STRUCTURE_DEFAULTS:
            if d[name] == STRUCTURE_DEFAULTS[name]:
                del d[name]
        import hashlib  # here: a command line that is only parsed needs no key

        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:32]

    def with_formats(self, formats: Sequence[str]) -> JobSpec:
        """This job writing ``formats`` instead."""
        return replace(self, outputs=Outputs(tuple(formats)))

    def with_source(self, source: Source | None) -> JobSpec:
        """This job reading ``source`` instead."""
        return replace(self, source=source)


#: Fields of :class:`Structures` besides ``level``, at their defaults: a job of one level.
STRUCTURE_DEFAULTS: dict[str, Any] = {
    f.name: f.default for f in fields(Structures) if f.name != "level"
}


def _plain(value: Any) -> Any:
    """Tuples as lists, numpy scalars as Python numbers: what JSON keeps."""
    if isinstance(value, tuple | list):
        return [_plain(v) for v in value]
    np = sys.modules.get("numpy")  # not loaded: no value can be a numpy scalar
    if np is not None and isinstance(value, np.generic):
        return value.item()
    return value
