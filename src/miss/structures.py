"""Several structures in one scene: iso-levels, their components, label maps.

``extract_scene`` is the one entry point. A scene's parts come from

- each iso-level of the volume (skin at one level, bone at another): the lower
  levels translucent so the higher ones show through; with ``components`` a
  level is cleaned (``largest``) or split into one part per piece (``split``,
  largest first), pieces under ``min_size_mm3`` left out;
- a label map (the volume itself, or a segmentation laid over it in patient mm):
  one part per label, boundaries shared with the neighbours
  (:mod:`miss.labelmap`), named and coloured from a label table (:mod:`miss.labels`).

Every part is smoothed (windowed sinc, optional) and decimated on its own
terms; the reports say by how much and at what measured error.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import ndimage

from miss.components import check_components, relabel_components, select_components
from miss.decimate import METHODS, DecimationReport, decimate
from miss.errors import BadParameter, EmptySurface
from miss.labelmap import (
    MEASURE_SAMPLES,
    LabelSurface,
    align_labels,
    label_counts,
    label_surfaces,
)
from miss.labels import (
    BONE,
    PALETTE,
    SKIN,
    SOFT_TISSUE,
    LabelTable,
    TableSpec,
    describe,
    resolve_table,
)
from miss.scene import DEFAULT_SCENE_TITLE, Part, Scene
from miss.smooth import VOLUME_TOLERANCE, check_smoothing, smooth_mesh
from miss.surface import extract_surface
from miss.types import Mesh, Volume

#: Windowed-sinc iterations when none are asked for: label maps come out of surface
#: nets as voxel blocks, threshold surfaces are already interpolated.
LABEL_SMOOTHING = 20
#: Opacity of every iso-level below the highest when there are several.
TRANSLUCENT = 0.35


@dataclass(frozen=True)
class SceneOptions:
    """How to build a scene; see :func:`extract_scene` for each field."""

    levels: tuple[float, ...] = ()
    labels: str | tuple[int, ...] | None = None
    components: str = "all"
    min_size_mm3: float = 0.0
    max_parts: int = 100
    smooth: int | None = None
    passband: float = 0.1
    decimate: str = "quadric"
    reduce: float = 0.9
    error_bound: float = 0.0002
    max_error: float = 0.01
    sample_rate: int | tuple[int, int, int] = 1
    slices: tuple[int, int] | None = None
    roi: tuple[int, int, int, int, int, int] | None = None
    measure: bool = True

    def __post_init__(self) -> None:
        levels = (self.levels,) if isinstance(self.levels, int | float) else tuple(self.levels)
        if not all(isinstance(v, int | float) and np.isfinite(v) for v in levels):
            raise BadParameter(f"levels must be finite numbers, got {self.levels!r}.")
        object.__setattr__(self, "levels", tuple(float(v) for v in levels))
        object.__setattr__(self, "labels", parse_labels(self.labels))
        check_components(self.components, self.min_size_mm3, self.max_parts)
        check_smoothing(0 if self.smooth is None else self.smooth, self.passband)
        if self.decimate not in METHODS:
            raise BadParameter(
                f"decimate must be one of {', '.join(METHODS)}, got {self.decimate!r}."
            )


@dataclass(frozen=True)
class SceneBuild:
    """A scene with what it took: one decimation report per part, seconds per stage."""

    scene: Scene
    reports: tuple[DecimationReport, ...]
    seconds: dict[str, float] = field(default_factory=dict)


def parse_labels(labels: str | Sequence[int] | int | None) -> str | tuple[int, ...] | None:
    """``None``, ``"all"``, ``"1,4,7"``, ``7`` or ``[1, 4, 7]`` -> None, "all" or sorted ids."""
    if labels is None or labels == "all":
        return labels
    if isinstance(labels, int) and not isinstance(labels, bool):
        labels = [labels]
    try:
        ids = (
            [int(p) for p in labels.split(",")]
            if isinstance(labels, str)
            else [int(p) for p in labels]
        )
    except (TypeError, ValueError):
        raise BadParameter(
            f"labels must be 'all' or label numbers such as 1,4,7; got {labels!r}."
        ) from None
    if not ids or min(ids) < 1:
        raise BadParameter(
            f"label numbers are whole numbers >= 1 (0 is background); got {labels!r}."
        )
    return tuple(sorted(set(ids)))


def extract_scene(
    volume: Volume,
    levels: float | Sequence[float] | None = None,
    labels: str | Sequence[int] | None = None,
    *,
    label_map: Volume | None = None,
    table: TableSpec = None,
    title: str | None = None,
    **options: Any,
) -> Scene:
    """Named, coloured structures of ``volume`` as one scene.

    Parameters
    ----------
    volume : Volume
        A scan (levels in its units, HU for CT) or an integer label map.
    levels : float or sequence of float, optional
        Iso-levels, one structure each; lower ones translucent when there are several.
    labels : "all", "1,4,7" or sequence of int, optional
        Labels to build (from ``label_map``, else from ``volume`` itself). With
        neither ``levels`` nor ``labels``, a label map gives all its labels.
    label_map : Volume, optional
        A segmentation of ``volume``; resampled onto its grid by nearest
        neighbour in patient mm, so a map covering fewer slices still fits.
    table : None, "totalseg", path or mapping
        Label names and colours (:func:`miss.labels.resolve_table`): a colour-table
        file, a NIfTI label map (the table in its header), TotalSegmentator's
        list, or {label: name}. A Volume has no file name to look beside, so
        None gives ``label N`` and the palette.
    title : str, optional
    **options
        Fields of :class:`SceneOptions`: ``components`` ("all", "largest",
        "split"), ``min_size_mm3``, ``max_parts``, ``smooth`` (windowed-sinc
        iterations; default 20 for label maps, 0 for levels), ``passband``,
        ``decimate``, ``reduce``, ``error_bound``, ``max_error``,
        ``sample_rate``, ``slices`` (1-based inclusive), ``roi``, ``measure``.

    Returns
    -------
    Scene
        Parts with closed meshes in LPS mm: levels first (lowest first; pieces
        largest first), then labels by number.
    """
    levels = () if levels is None else levels
    spec = SceneOptions(levels=levels, labels=labels, **options)  # type: ignore[arg-type]
    return build_scene(volume, spec, label_map=label_map, table=table, title=title).scene


def build_scene(
    volume: Volume,
    options: SceneOptions,
    *,
    label_map: Volume | None = None,
    table: TableSpec = None,
    title: str | None = None,
) -> SceneBuild:
    """:func:`extract_scene` with the per-part reports and timings (for the pipeline and CLI)."""
    start = time.perf_counter()
    labels_volume = _label_source(volume, options, label_map)
    if not options.levels and labels_volume is None:
        raise BadParameter(
            "nothing to extract: give a threshold in the volume's units (--level, levels=) "
            "or labels of a label map (--labels, labels=); this volume is not a label map."
        )
    volume = crop_volume(volume, options.sample_rate, options.slices, options.roi)
    built: list[tuple[Part, DecimationReport]] = []
    notes: list[str] = []
    ranked = sorted(options.levels)
    for level in options.levels:
        style = level_style(level, ranked.index(level), len(ranked), volume.meta.get("units", ""))
        built += _level_parts(volume, level, style, options, notes)
    if labels_volume is not None:
        labels_volume = crop_volume(labels_volume, options.sample_rate, options.slices, options.roi)
        built += _label_parts(labels_volume, options, resolve_table(table), notes)
    decimating = sum(report.seconds + report.measure_seconds for _, report in built)
    scene = Scene(tuple(p for p, _ in built), title or DEFAULT_SCENE_TITLE, tuple(notes))
    total = time.perf_counter() - start
    seconds = {"surface": total - decimating, "decimate": decimating}
    return SceneBuild(scene, tuple(r for _, r in built), seconds)


def _label_source(volume: Volume, options: SceneOptions, label_map: Volume | None) -> Volume | None:
    """The label map on ``volume``'s grid, or None when the scene has no label parts."""
    if label_map is not None:
        return align_labels(label_map, volume)
    if options.labels is not None:
        return volume
    if not options.levels and label_counts(volume) is not None:
        return volume  # a label map with nothing asked for: all its labels
    return None


def crop_volume(
    volume: Volume,
    sample_rate: int | Sequence[int] = 1,
    slices: tuple[int, int] | None = None,
    roi: Sequence[int] | None = None,
) -> Volume:
    """The region (1-based inclusive slices, 0-based inclusive ROI) at the sample rate.

    Striding keeps every n-th voxel, which for a label map is nearest-neighbour
    subsampling; the affine is adjusted so positions stay in patient mm.
    """
    steps = (sample_rate,) * 3 if isinstance(sample_rate, int) else tuple(sample_rate)
    if len(steps) != 3 or any(not isinstance(s, int) or s < 1 for s in steps):
        raise BadParameter(
            f"sample rate must be one whole number >= 1 or three, got {sample_rate!r}."
        )
    box = [(0, d - 1) for d in volume.dims]
    if roi is not None:
        box = [(int(roi[2 * a]), int(roi[2 * a + 1])) for a in range(3)]
    if slices is not None:
        box[2] = (max(box[2][0], slices[0] - 1), min(box[2][1], slices[1] - 1))
    if box == [(0, d - 1) for d in volume.dims] and steps == (1, 1, 1):
        return volume
    for axis, (lo, hi) in enumerate(box):
        if not 0 <= lo < hi < volume.dims[axis] or (hi - lo) // steps[axis] < 1:
            raise BadParameter(
                f"region {lo}..{hi} along {'xyz'[axis]} (sample rate {steps[axis]}) leaves fewer "
                f"than 2 voxels of 0..{volume.dims[axis] - 1}; widen the region or lower the rate."
            )
    data = volume.data[tuple(slice(lo, hi + 1, s) for (lo, hi), s in zip(box, steps, strict=True))]
    shift = np.eye(4)
    shift[:3, :3] = np.diag(np.asarray(steps, dtype=np.float64))
    shift[:3, 3] = [lo for lo, _ in box]
    return Volume(np.asfortranarray(data), volume.affine @ shift, volume.meta, volume.patient)


def level_style(
    level: float, rank: int, count: int, units: str
) -> tuple[str, tuple[float, float, float], float]:
    """Name, colour and opacity of an iso-level structure.

    In HU the level says what it is (below -200 skin, from 150 bone, soft tissue
    between); in unknown units the rank does (lowest skin, highest bone). All
    but the highest of several levels are translucent.
    """
    if units == "HU":
        kind = "skin" if level < -200 else "bone" if level >= 150 else "soft tissue"
        name = f"{kind} ({level:g} HU)"
    else:
        kind = "bone" if rank == count - 1 else "skin" if rank == 0 else "soft tissue"
        name = f"level {level:g}"
    color = {"skin": SKIN, "bone": BONE}.get(kind, SOFT_TISSUE)
    opacity = TRANSLUCENT if count > 1 and rank < count - 1 else 1.0
    return name, color, opacity


def _level_parts(
    volume: Volume,
    level: float,
    style: tuple[str, tuple[float, float, float], float],
    options: SceneOptions,
    notes: list[str],
) -> list[tuple[Part, DecimationReport]]:
    """One iso-level: the whole surface, its largest piece, or one part per piece."""
    name, color, opacity = style
    if options.components == "all" and options.min_size_mm3 == 0:
        meshes = [extract_surface(volume, level)]
    else:
        meshes = _component_meshes(volume, level, options, notes, name)
    out = []
    for rank, mesh in enumerate(meshes):
        split = options.components == "split" and len(meshes) > 1
        part_name = f"{name} {rank + 1}" if split else name
        part_color = PALETTE[rank % len(PALETTE)] if split else color
        smoothed = _smoothed(mesh, options.smooth or 0, options.passband, part_name, notes)
        decimated, report = _decimated(smoothed, options)
        out.append((Part(part_name, decimated, part_color, opacity), report))
    return out


def _component_meshes(
    volume: Volume, level: float, options: SceneOptions, notes: list[str], name: str
) -> list[Mesh]:
    """Surfaces of the chosen voxel components above ``level``, largest first."""
    voxel_mm3 = abs(float(np.linalg.det(volume.affine[:3, :3])))
    mask = volume.data > level
    picked = select_components(
        mask, options.components, options.min_size_mm3 / voxel_mm3, options.max_parts
    )
    if not picked.kept:
        raise EmptySurface(
            f"no piece of {name} is at least {options.min_size_mm3:g} mm³; lower the minimum size."
        )
    if picked.dropped:
        notes.append(f"{name}: {picked.dropped} smaller piece(s) left out")
    groups = [[c] for c in picked.kept] if options.components == "split" else [picked.kept]
    return [_component_surface(volume, level, picked.labelled, ids) for ids in groups]


def _component_surface(volume: Volume, level: float, labelled: np.ndarray, ids: list[int]) -> Mesh:
    """The surface of the voxel components ``ids``: crop around them, blank the others.

    With 26-connectivity no marching cube holds voxels of two components, so
    setting the others below the level changes no triangle of these.
    """
    inside = np.isin(labelled, ids)
    (found,) = ndimage.find_objects(inside.view(np.int8))
    region = tuple(
        slice(max(sl.start - 1, 0), min(sl.stop + 1, n))  # one voxel below the level all round
        for sl, n in zip(found, volume.dims, strict=True)
    )
    data = np.array(volume.data[region], order="F")
    others = (labelled[region] > 0) & ~inside[region]
    if np.issubdtype(data.dtype, np.integer) and np.iinfo(data.dtype).min < level:
        data[others] = np.iinfo(data.dtype).min
    else:
        data = data.astype(np.float32, order="F")
        data[others] = min(float(data.min()), level - 1.0)
    shift = np.eye(4)
    shift[:3, 3] = [sl.start for sl in region]
    return extract_surface(Volume(data, volume.affine @ shift, volume.meta), level)


def _smoothed(mesh: Mesh, iterations: int, passband: float, name: str, notes: list[str]) -> Mesh:
    """Windowed-sinc smoothing with its volume check (a note when it changed > 2 %)."""
    smoothed, change = smooth_mesh(mesh, iterations, passband)
    if abs(change) > VOLUME_TOLERANCE:
        notes.append(f"{name}: smoothing changed the volume by {change:+.1%}")
    return smoothed


def _decimated(mesh: Mesh, options: SceneOptions) -> tuple[Mesh, DecimationReport]:
    return decimate(
        mesh,
        options.decimate,
        options.reduce,
        options.error_bound,
        max_error=options.max_error,
        measure=options.measure,
        samples=MEASURE_SAMPLES,
    )


def _label_parts(
    labels_volume: Volume, options: SceneOptions, table: LabelTable | None, notes: list[str]
) -> list[tuple[Part, DecimationReport]]:
    """One part per chosen label (per piece with ``split``), boundaries shared."""
    chosen = _chosen_labels(labels_volume, options.labels, notes)
    data, origin = labels_volume.data, {label: (label, 0) for label in chosen}
    if options.components != "all" or options.min_size_mm3 > 0:
        voxel_mm3 = abs(float(np.linalg.det(labels_volume.affine[:3, :3])))
        data, origin, dropped = relabel_components(
            data, chosen, options.components, options.min_size_mm3 / voxel_mm3, options.max_parts
        )
        if dropped:
            notes.append(f"{dropped} small piece(s) of labels left out")
    work = replace(labels_volume, data=data)
    iterations = LABEL_SMOOTHING if options.smooth is None else options.smooth
    surfaces = label_surfaces(
        work, sorted(origin, key=lambda i: origin[i]), smooth=iterations, passband=options.passband,
        method=options.decimate, reduce=options.reduce, error_bound=options.error_bound,
        max_error=options.max_error, measure=options.measure,
    )  # fmt: skip
    return _named_parts(surfaces, origin, table, label_counts(work) or {}, work, notes)


def _named_parts(
    surfaces: list[LabelSurface],
    origin: dict[int, tuple[int, int]],
    table: LabelTable | None,
    counts: dict[int, int],
    work: Volume,
    notes: list[str],
) -> list[tuple[Part, DecimationReport]]:
    """Parts named and coloured from the table; notes the labels smoothing shrank > 2 %."""
    voxel_ml = abs(float(np.linalg.det(work.affine[:3, :3]))) / 1000
    pieces: dict[int, int] = {}
    for label, _ in origin.values():
        pieces[label] = pieces.get(label, 0) + 1
    out, changed = [], []
    for surface in surfaces:
        label, rank = origin[surface.label]
        info = describe(label, table)
        name = f"{info.name} {rank + 1}" if pieces[label] > 1 else info.name
        out.append((Part(name, surface.mesh, info.color, info.opacity, label), surface.report))
        # Unsmoothed surface nets enclose exactly the voxels: the change is smoothing's.
        voxels = counts.get(surface.label, 0) * voxel_ml
        change = Part(name, surface.full).volume_ml / voxels - 1 if voxels else 0.0
        if abs(change) > VOLUME_TOLERANCE:
            changed.append(f"{name} {change:+.0%}")
    if changed:
        notes.append("smoothing changed the volume of: " + ", ".join(changed))
    return out


def _chosen_labels(
    labels_volume: Volume, wanted: str | tuple[int, ...] | None, notes: list[str]
) -> list[int]:
    """The labels to build: all present, or the asked-for ones that are present."""
    counts = label_counts(labels_volume)
    if counts is None:
        raise BadParameter(
            "the labels must come from a label map: whole numbers 0..65535 with at most 512 "
            f"distinct values (this holds {labels_volume.data.dtype} data); for a scan give levels."
        )
    if wanted is None or wanted == "all":
        chosen = sorted(counts)
    else:
        chosen = [label for label in wanted if label in counts]
        missing = [label for label in wanted if label not in counts]
        if missing:
            notes.append(f"label(s) {', '.join(map(str, missing))} not in the label map")
    if not chosen:
        raise EmptySurface(
            f"none of the labels {wanted} is in the label map (present: {sorted(counts)[:20]}); "
            "pick labels from 'miss info --json'."
        )
    return chosen


def combined_report(reports: Sequence[DecimationReport]) -> DecimationReport:
    """One report for a whole scene: counts and seconds summed, the worst max error,
    the triangle-weighted mean error; None where any part was not measured."""
    if not reports:
        raise EmptySurface("the scene has no parts to report on.")
    first = reports[0]
    t_in = sum(r.triangles_in for r in reports)
    t_out = sum(r.triangles_out for r in reports)
    measured = all(r.max_error_mm is not None for r in reports)
    return DecimationReport(
        method=first.method,
        reduce=first.reduce,
        error_bound=first.error_bound,
        triangles_in=t_in,
        triangles_out=t_out,
        achieved_reduction=1.0 - t_out / max(t_in, 1),
        final_bound_mm=max(r.final_bound_mm for r in reports),
        max_error_mm=max(r.max_error_mm or 0.0 for r in reports) if measured else None,
        mean_error_mm=(
            sum((r.mean_error_mm or 0.0) * r.triangles_out for r in reports) / max(t_out, 1)
            if measured
            else None
        ),
        seconds=sum(r.seconds for r in reports),
        measure_seconds=sum(r.measure_seconds for r in reports),
    )
