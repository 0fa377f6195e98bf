"""Several structures in one scene: iso-levels, their components, label maps.

``extract_scene`` is the one entry point. A scene's parts come from

- each iso-level of the volume (skin at one level, bone at another): the lower
  levels translucent so the higher ones show through; with ``components`` a
  level is cleaned (``largest``) or split into one part per piece (``split``,
  largest first), pieces under ``min_size_mm3`` left out;
- a label map (the volume itself, or a segmentation laid over it in patient mm):
  one part per label, boundaries shared with the neighbours
  (:mod:`miss.structures.labelmap`), named and coloured from a label table (:mod:`miss.structures.labels`).

Every part is smoothed (windowed sinc, optional) and decimated on its own
terms; the reports say by how much and at what measured error.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from miss.decimate import (
    SAMPLES,
    DecimationReport,
    Heard,
    decimate,
    measured,
    measuring_later,
)
from miss.errors import BadParameter, EmptySurface
from miss.geometry import locality_order
from miss.measure import measurer, native
from miss.scene import DEFAULT_SCENE_TITLE, Part, Scene
from miss.smooth import VOLUME_TOLERANCE, displacement, smooth_mesh
from miss.spec import LABEL_SMOOTHING, Decimation, JobSpec, Structure
from miss.structures.block_components import blockwise_components, component_surfaces
from miss.structures.components import relabel_components, select_components
from miss.structures.labelmap import (
    MEASURE_SAMPLES,
    LabelSurface,
    align_labels,
    label_counts,
    label_surfaces,
)
from miss.structures.labels import (
    BONE,
    PALETTE,
    SKIN,
    SOFT_TISSUE,
    LabelTable,
    TableSpec,
    describe,
    resolve_table,
)
from miss.surface import extract_surface
from miss.surface.blockwise import (
    BlockDecimation,
    BlockRun,
    decimated_surface_of,
    in_blocks,
    surface_of,
)
from miss.types import Mesh, Volume, in_memory

if TYPE_CHECKING:
    from miss.measure import Side
    from miss.measure.measurer import RemoteSide

#: Opacity of every iso-level below the highest when there are several.
TRANSLUCENT = 0.35


@dataclass(frozen=True)
class Source:
    """A part's surface before decimation, the samples a side its measurement takes, and
    (when it was started) that measurement's half on this surface, being made meanwhile
    (:func:`miss.decimate.measuring_later`, or in :mod:`miss.measure.measurer`'s process)."""

    mesh: Mesh
    samples: int
    side: Future[Side] | RemoteSide | None = None


@dataclass(frozen=True)
class SceneBuild:
    """A scene with what it took: one decimation report per part, seconds per stage.

    Built with ``measure=False``, it keeps each part's :class:`Source` in ``sources``, for
    :meth:`measured` to use later.
    """

    scene: Scene
    reports: tuple[DecimationReport, ...]
    seconds: dict[str, float] = field(default_factory=dict)
    sources: tuple[Source, ...] = ()

    def measured(self) -> SceneBuild:
        """This build with each part's deviation from its undecimated surface measured (mm);
        ``seconds["measure"]`` says how long that took (with a held bound's check, made
        while decimating)."""
        if not self.sources:
            return self
        start = time.perf_counter()
        parts = zip(self.reports, self.scene.parts, self.sources, strict=True)
        reports = tuple(
            measured(r, source.mesh, part.mesh, source.samples, source.side)
            for r, part, source in parts
        )
        spent = self.seconds.get("measure", 0.0) + time.perf_counter() - start  # a check's too
        seconds = {**self.seconds, "measure": spent}
        return replace(self, reports=reports, seconds=seconds, sources=())


#: Parts of one build whose measurement is started while it decimates (see
#: :class:`_Ahead`); a split surface may have 100 parts, each measured with 100,000 samples a
#: side, and the rest are measured after decimating.
SIDES_AHEAD = 8


class _Ahead:
    """The measurements' halves a build starts while it decimates, for its first
    :data:`SIDES_AHEAD` parts (the largest, as parts come).

    In a process that has the native kernels (:mod:`miss.measure._native`) or numba loaded
    already (a server's worker, warmed up), on one thread for the build, one after another
    (:func:`miss.decimate.measuring_later`). Without the native kernels, in a fresh one
    (``miss convert --measure``) a thread would import numba while the
    decimation runs, and the decimation's own loops, which take numba once it is there,
    would wait for that import (measured: the job as a whole was no sooner, 2.80 against
    2.78 s); there the parts go to a measuring process (:mod:`miss.measure.measurer`), which
    starts numba on the other core and measures them, or, where none starts, are measured
    after the GLB."""

    def __init__(self) -> None:
        self.pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="miss-side")
        self.left = SIDES_AHEAD

    def start(self, mesh: Mesh, samples: int) -> Future[Side] | RemoteSide | None:
        if self.left <= 0:
            return None
        self.left -= 1
        if "numba" in sys.modules or native():
            return measuring_later(mesh, samples, self.pool)
        child = measurer.shared()
        return None if child is None else child.side(mesh, samples)

    def close(self) -> None:
        self.pool.shutdown(wait=False)  # what was started is still made


#: A built part: the part, its decimation report, its :class:`Source`.
Built = tuple[Part, DecimationReport, Source]


def extract_scene(
    volume: Volume,
    levels: float | Sequence[float] | None = None,
    labels: str | Sequence[int] | None = None,
    *,
    label_map: Volume | None = None,
    table: TableSpec = None,
    title: str | None = None,
    measure: bool = True,
    slices: tuple[int, int] | None = None,
    **form: Any,
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
        Label names and colours (:func:`miss.structures.labels.resolve_table`): a colour-table
        file, a NIfTI label map (the table in its header), TotalSegmentator's
        list, or {label: name}. A Volume has no file name to look beside, so
        None gives ``label N`` and the palette.
    title : str, optional
    measure : bool
        Measure each part's deviation from its undecimated surface (mm).
    slices : (start, end), optional
        1-based inclusive slice range (``start_slice``/``end_slice`` of the form).
    **form
        Fields of the job form (:class:`miss.spec.JobSpec`): ``components`` ("all",
        "largest", "split"), ``min_size_mm3``, ``max_parts``, ``smooth``
        (windowed-sinc iterations; default 20 for label maps, 0 for levels),
        ``passband``, ``parts``, ``decimate``, ``reduce``, ``error_bound``,
        ``max_error``, ``sample_rate``, ``start_slice``, ``end_slice``, ``roi``.

    Returns
    -------
    Scene
        Parts with closed meshes in LPS mm: levels first (lowest first; pieces
        largest first), then labels by number.
    """
    levels = [levels] if isinstance(levels, int | float) else list(levels or [])
    if not levels and labels is None and not form.get("parts"):
        if label_map is None and label_counts(volume) is None:
            raise BadParameter(
                "nothing to extract: give a threshold in the volume's units (--level, levels=) "
                "or labels of a label map (--labels, labels=); this volume is not a label map."
            )
        labels = "all"  # a label map with nothing asked for: all its labels
    if slices is not None:
        form |= {"start_slice": slices[0], "end_slice": slices[1]}
    spec = JobSpec.of(levels=levels or None, labels=labels, **form)
    return build_scene(
        volume, spec, label_map=label_map, table=table, title=title, measure=measure
    ).scene


def build_scene(
    volume: Volume,
    spec: JobSpec,
    *,
    label_map: Volume | None = None,
    table: TableSpec = None,
    title: str | None = None,
    measure: bool = True,
    blocks: BlockRun | None = None,
    measure_later: bool = False,
    progress: Heard | None = None,
    ordered: bool = True,
) -> SceneBuild:
    """The scene ``spec`` asks for, with the per-part reports and timings: every
    threshold part of the region, then the label parts (built together). ``blocks``
    runs the threshold surfaces block by block (:mod:`miss.surface.blockwise`).
    ``measure_later`` (with ``measure`` False): the caller measures the build after
    (:meth:`SceneBuild.measured`), so the half of a measurement that needs only a part's
    surface before decimation is started as soon as that surface exists. ``progress(stage,
    fraction)`` hears the decimation's ("decimate", "check") of the threshold parts.
    ``ordered``: the scene's meshes in :func:`ordered_scene`'s layout (the caller lays
    them out later when False)."""
    start = time.perf_counter()
    items = spec.structures.items
    label_items = [p for p in items if p.labels is not None]
    labels_volume = None
    if label_items:  # aligned before the crop, so the map's region is the volume's
        labels_volume = align_labels(label_map, volume) if label_map is not None else volume
    region = spec.region.apply(volume)
    built: list[Built] = []
    notes: list[str] = []
    ranked = sorted(p.level for p in items if p.level is not None)
    ahead = _Ahead() if measure_later and not measure else None
    try:
        for item in items:
            if item.level is not None:
                style = level_style(
                    item.level, ranked.index(item.level), len(ranked), volume.meta.get("units", "")
                )
                built += _level_parts(
                    region, item, style, spec.decimation, measure, notes, blocks, ahead, progress
                )
    finally:
        if ahead is not None:
            ahead.close()
    if labels_volume is not None:
        labels_region = in_memory(spec.region.apply(labels_volume))  # not blockwise yet
        built += _label_parts(
            labels_region, label_items, spec.decimation, measure, resolve_table(table), notes
        )
    decimating = sum(b[1].seconds for b in built)
    checking = sum(b[1].measure_seconds for b in built)  # a held bound's check, measured
    scene = Scene(tuple(b[0] for b in built), title or DEFAULT_SCENE_TITLE, tuple(notes))
    ordering = time.perf_counter()
    scene = ordered_scene(scene) if ordered else scene
    ordering = time.perf_counter() - ordering
    total = time.perf_counter() - start
    seconds = {"surface": total - decimating - checking - ordering, "decimate": decimating}
    if ordered:
        seconds["order"] = ordering
    if checking:
        seconds["measure"] = checking
    sources = () if measure else tuple(b[2] for b in built)
    return SceneBuild(scene, tuple(b[1] for b in built), seconds, sources)


def ordered_scene(scene: Scene) -> Scene:
    """``scene`` laid out for every file it becomes: each part's triangles in vertex-cache
    order, its vertices in first-use order (:func:`~miss.geometry.locality_order`)."""
    parts = tuple(replace(part, mesh=locality_order(part.mesh)) for part in scene.parts)
    return replace(scene, parts=parts)


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
    item: Structure,
    style: tuple[str, tuple[float, float, float], float],
    decimation: Decimation,
    measure: bool,
    notes: list[str],
    blocks: BlockRun | None = None,
    ahead: _Ahead | None = None,
    progress: Heard | None = None,
) -> list[Built]:
    """One iso-level: the whole surface, its largest piece, or one part per piece.
    The part's own name, colour and opacity win over the level's style. ``ahead``: the
    parts are measured after, their measurements started there (see :func:`build_scene`'s
    ``measure_later``)."""
    assert item.level is not None
    name = item.name or style[0]
    color = item.color or style[1]
    opacity = style[2] if item.opacity is None else item.opacity
    if item.components == "all" and item.min_size_mm3 == 0:
        if in_blocks(volume, blocks) and _blocks_decimate(item, decimation):
            made, report, welded = _decimated_in_blocks(
                volume, item.level, decimation, blocks, name, notes, progress
            )
            return [(Part(name, made, color, opacity), report, Source(welded, SAMPLES))]
        # A decimated mesh gets new normals from its faces: gradients only for "none".
        normals = decimation.method == "none"
        meshes = [surface_of(volume, item.level, normals=normals, blocks=blocks)]
    else:
        meshes = _component_meshes(volume, item, notes, name, blocks)
    out = []
    for rank, mesh in enumerate(meshes):
        split = item.components == "split" and len(meshes) > 1
        part_name = f"{name} {rank + 1}" if split else name
        part_color = PALETTE[rank % len(PALETTE)] if split and item.color is None else color
        smoothed = _smoothed(mesh, item.smooth or 0, item.passband, part_name, notes)
        moved = displacement(mesh, smoothed) if item.smooth else None
        # a guaranteed bound is checked (and held) while decimating, whatever ``measure`` says
        checked = measure or decimation.schedule == "guaranteed"
        unchanged = decimation.method == "none" or smoothed.n_triangles == 0
        side = None if checked or unchanged or ahead is None else ahead.start(smoothed, SAMPLES)
        decimated, report = decimate(
            smoothed, decimation.method, decimation.reduce, decimation.error_bound,
            max_error=decimation.max_error, schedule=decimation.schedule,
            measure=checked, progress=progress,
        )  # fmt: skip
        part = Part(part_name, decimated, part_color, opacity, smoothed_mm=moved)
        out.append((part, report, Source(smoothed, SAMPLES, side)))
    return out


def _blocks_decimate(item: Structure, decimation: Decimation) -> bool:
    """Whether a blockwise surface is decimated in its blocks first: under a guaranteed
    bound (its share of the bound is known from the blocks' extents) and unsmoothed (the
    smoothing runs on the whole surface, before any decimation)."""
    return decimation.method != "none" and decimation.schedule == "guaranteed" and not item.smooth


def _decimated_in_blocks(
    volume: Volume,
    level: float,
    decimation: Decimation,
    blocks: BlockRun | None,
    name: str,
    notes: list[str],
    progress: Heard | None = None,
) -> tuple[Mesh, DecimationReport, Mesh]:
    """A level's surface decimated in two stages: each block where it was made, its border
    held, to half the bound (:func:`miss.surface.blockwise.blockwise_decimated`); then the welded
    mesh, across the blocks, to what the blocks left of the bound and of the triangles.

    The report's maximum is the two stages' measured maxima added: the output lies within
    that of the full-resolution surface, both ways (each stage's deviation is a distance
    between surfaces, and distances add up), which is never in one place to measure.
    """
    wanted = BlockDecimation(decimation.method, decimation.reduce, decimation.error_bound)
    welded, stage = decimated_surface_of(volume, level, wanted, blocks)
    bound_mm = decimation.error_bound * stage.diagonal_mm  # of the full surface
    left_mm = bound_mm - stage.max_mm
    target = (1.0 - decimation.reduce) * stage.triangles_in
    again = min(max(0.0, 1.0 - target / max(welded.n_triangles, 1)), 0.999)
    out, across = decimate(
        welded, decimation.method, again, max(left_mm, 0.0) / max(welded.diagonal(), 1e-12),
        schedule="guaranteed", measure=True, progress=progress,
    )  # fmt: skip
    report = replace(
        across,
        reduce=decimation.reduce,
        error_bound=decimation.error_bound,
        triangles_in=stage.triangles_in,
        achieved_reduction=1.0 - across.triangles_out / max(stage.triangles_in, 1),
        final_bound_mm=bound_mm,
        bound_mm=bound_mm,
        max_error_mm=stage.max_mm + (across.max_error_mm or 0.0),
        mean_error_mm=stage.mean_mm + (across.mean_error_mm or 0.0),
        seconds=stage.seconds + across.seconds,
        stopped_by="reduce" if across.triangles_out <= target + 1e-9 else "bound",
    )
    notes.append(
        f"{name}: decimated in its blocks (borders held), then across them; the error is "
        "the two stages' measured errors added (at most that)"
    )
    return out, report, welded


def _component_meshes(
    volume: Volume,
    item: Structure,
    notes: list[str],
    name: str,
    blocks: BlockRun | None = None,
) -> list[Mesh]:
    """Surfaces of the chosen voxel components above the level, largest first; block by
    block when :func:`~miss.surface.blockwise.in_blocks` (the same pieces and surfaces)."""
    assert item.level is not None
    voxel_mm3 = abs(float(np.linalg.det(volume.affine[:3, :3])))
    min_voxels = item.min_size_mm3 / voxel_mm3
    if in_blocks(volume, blocks):
        run = blocks or BlockRun()
        chosen = blockwise_components(
            volume, item.level, item.components, min_voxels, item.max_parts,
            block=run.block, scheduler=run.scheduler, progress=run.progress,
        )  # fmt: skip
        _note_components(chosen.groups, chosen.dropped, item, name, notes)
        return component_surfaces(
            volume, item.level, chosen, scheduler=run.scheduler, progress=run.progress
        )
    mask = volume.data > item.level
    picked = select_components(mask, item.components, min_voxels, item.max_parts)
    groups = [[c] for c in picked.kept] if item.components == "split" else [picked.kept]
    _note_components(picked.kept, picked.dropped, item, name, notes)
    return [_component_surface(volume, item.level, picked.labelled, ids) for ids in groups]


def _note_components(
    kept: Sequence[object], dropped: int, item: Structure, name: str, notes: list[str]
) -> None:
    """No piece kept is an error; pieces left out a note."""
    if not kept:
        raise EmptySurface(
            f"no piece of {name} is at least {item.min_size_mm3:g} mm³; lower the minimum size."
        )
    if dropped:
        notes.append(f"{name}: {dropped} smaller piece(s) left out")


def _component_surface(volume: Volume, level: float, labelled: np.ndarray, ids: list[int]) -> Mesh:
    """The surface of the voxel components ``ids``: crop around them, blank the others.

    With 26-connectivity no marching cube holds voxels of two components, so
    setting the others below the level changes no triangle of these.
    """
    from scipy import ndimage  # 0.3 s to load: only for a level's components

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


def _label_parts(
    labels_volume: Volume,
    items: list[Structure],
    decimation: Decimation,
    measure: bool,
    table: LabelTable | None,
    notes: list[str],
) -> list[Built]:
    """One part per chosen label (per piece with ``split``), boundaries shared. The label
    parts share their cleanup (:class:`~miss.spec.Structures` checks that)."""
    first = items[0]
    wanted: str | list[int] = "all"
    ids = [p.labels for p in items if isinstance(p.labels, tuple)]
    if len(ids) == len(items):
        wanted = sorted({i for each in ids for i in each})
    chosen = _chosen_labels(labels_volume, wanted, notes)
    data, origin = labels_volume.data, {label: (label, 0) for label in chosen}
    if first.components != "all" or first.min_size_mm3 > 0:
        voxel_mm3 = abs(float(np.linalg.det(labels_volume.affine[:3, :3])))
        data, origin, dropped = relabel_components(
            data, chosen, first.components, first.min_size_mm3 / voxel_mm3, first.max_parts
        )
        if dropped:
            notes.append(f"{dropped} small piece(s) of labels left out")
    work = replace(labels_volume, data=data)
    iterations = LABEL_SMOOTHING if first.smooth is None else first.smooth
    surfaces = label_surfaces(
        work, sorted(origin, key=lambda i: origin[i]), smooth=iterations, passband=first.passband,
        method=decimation.method, reduce=decimation.reduce, error_bound=decimation.error_bound,
        max_error=decimation.max_error, measure=measure, schedule=decimation.schedule,
    )  # fmt: skip
    styles = {p.labels[0]: p for p in items if isinstance(p.labels, tuple) and len(p.labels) == 1}
    parts = _named_parts(surfaces, origin, table, label_counts(work) or {}, work, notes)
    return [
        (_restyled(p, styles.get(p.label or 0), table), r, Source(surface.full, MEASURE_SAMPLES))
        for (p, r), surface in zip(parts, surfaces, strict=True)
    ]


def _restyled(part: Part, item: Structure | None, table: LabelTable | None) -> Part:
    """A label part with the name, colour and opacity its own entry gives (a piece of a
    split label keeps its number after the name)."""
    if item is None or (item.name, item.color, item.opacity) == (None, None, None):
        return part
    name = part.name
    if item.name:
        piece = name.removeprefix(describe(part.label or 0, table).name)
        name = item.name + (piece if piece != name else "")
    opacity = part.opacity if item.opacity is None else item.opacity
    return Part(name, part.mesh, item.color or part.color, opacity, part.label)


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
        assert info.color is not None  # describe fills it in
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


def _chosen_labels(labels_volume: Volume, wanted: str | list[int], notes: list[str]) -> list[int]:
    """The labels to build: all present, or the asked-for ones that are present."""
    counts = label_counts(labels_volume)
    if counts is None:
        raise BadParameter(
            "this volume is not a label map (labels are whole numbers 0..65535, at most 512 "
            f"distinct values; it holds {labels_volume.data.dtype} data): give a level (--level, "
            "'level': a threshold in its units, HU for CT) or a label map of it."
        )
    if wanted == "all":
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
    the triangle-weighted mean error; None where any part was not measured. Each part is
    held to its own bound (a fraction of its own diagonal): ``bound_mm`` is the largest,
    ``stopped_by`` "bound" when any part stopped at its bound."""
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
        schedule=first.schedule,
        bound_mm=max((r.bound_mm or 0.0) for r in reports),
        stopped_by="bound" if any(r.stopped_by == "bound" for r in reports) else first.stopped_by,
        bound_held=None
        if any(r.bound_held is None for r in reports)
        else all(r.bound_held for r in reports),
        rounds=max(r.rounds for r in reports),
        finished_with=_made_by(reports),
    )


def _made_by(reports: Sequence[DecimationReport]) -> str:
    """The methods that made a scene's parts, "/"-joined ("schroeder", "quadric/schroeder");
    a part kept whole ("none") counts only when every part was."""
    made = {r.finished_with or r.method for r in reports}
    return "/".join(sorted(made - {"none"} or made))
