"""The job run: ``run(volume, spec) -> JobResult`` and ``execute(spec, sink)``.

``execute`` is the one path every job takes, from ``miss convert`` and from the
server's workers alike: the spec's source loads the volume, :func:`run` builds the
scene (one level is a scene of one part) and encodes it, and a :class:`Sink` takes
the files (to paths on the command line, to the data folder in the server; back to a
PACS next). No web, no globals.

The order is the one a waiting physician needs: a coarse preview first when the sink
asks for one, then a large model's levels of detail, then the model's GLB, then (once the
sink's viewer has drawn it, when it has one) the other formats, the error measured
meanwhile on a second thread; the job is done once both are.
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Any, Protocol

from miss.decimate import DecimationReport
from miss.errors import BadParameter, EmptySurface
from miss.export import export
from miss.measure import measurer
from miss.scene import Scene
from miss.spec import JobSpec
from miss.structures.build import SceneBuild, build_scene, combined_report, ordered_scene
from miss.structures.labels import TableSpec
from miss.surface.blockwise import BlockRun, in_blocks
from miss.types import Mesh, Volume

Progress = Callable[[str, float], None]
#: A format's writer options, e.g. ``{"glb": {"compress": True}}``.
ExportOptions = Mapping[str, Mapping[str, Any]]


def _no_progress(stage: str, fraction: float) -> None:
    return None


#: Each stage's share of a job's progress, in the order a job meets them: what the
#: callbacks inside report as a fraction of their stage becomes a fraction of the job.
#: ("check" is the decimation's own check of a guaranteed bound; "measure" the error
#: measured at the end, beside the files.)
STAGE_SPANS: dict[str, tuple[float, float]] = {
    "read": (0.0, 0.0),
    "preview": (0.0, 0.05),
    "surface": (0.05, 0.30),
    "decimate": (0.30, 0.60),
    "check": (0.60, 0.65),
    "lod": (0.65, 0.75),
    "write": (0.75, 0.90),
    "measure": (0.90, 1.0),
    "done": (1.0, 1.0),
}


def staged(progress: Progress) -> Progress:
    """``progress`` hearing (stage, fraction of the job) from callbacks that report
    (stage, fraction of that stage), never going back (a second part's surface, a second
    round of decimation, hold the bar where it is); a stage not in :data:`STAGE_SPANS`
    passes as it is."""
    furthest = [0.0]

    def heard(stage: str, fraction: float) -> None:
        span = STAGE_SPANS.get(stage)
        if span is None:
            progress(stage, fraction)
            return
        lo, hi = span
        furthest[0] = max(furthest[0], lo + (hi - lo) * min(max(fraction, 0.0), 1.0))
        progress(stage, furthest[0])

    return heard


@dataclass
class JobResult:
    """The scene, its decimation report (all parts together), the encoded files and the
    seconds each stage took."""

    scene: Scene
    report: DecimationReport
    artifacts: dict[str, bytes]
    seconds: dict[str, float]
    metadata: dict[str, str] = field(default_factory=dict)  # provenance in the files
    title: str | None = None  # the title the writers were given

    @cached_property
    def mesh(self) -> Mesh:
        """Every part as one mesh (``labels`` holds each face's part index)."""
        return self.scene.merged()

    def stats(self) -> dict[str, Any]:
        """Triangles, vertices, seconds, bytes per format, the decimation with its measured
        error, and per part its name, label, colour, opacity, triangles, mL and cm²."""
        return {
            "triangles": self.scene.n_triangles,
            "vertices": self.scene.n_vertices,
            "seconds": dict(self.seconds),
            "bytes": {fmt: len(data) for fmt, data in self.artifacts.items()},
            "decimation": self.report.summary(),
            "parts": self.scene.summary(),
            "notes": list(self.scene.notes),
        }


def run(
    volume: Volume,
    spec: JobSpec,
    progress: Progress | None = None,
    *,
    title: str | None = None,
    metadata: dict[str, str] | None = None,
    label_map: Volume | None = None,
    table: TableSpec = None,
    export_options: ExportOptions | None = None,
    sink: Sink | None = None,
    measure: bool = True,
    blocks: BlockRun | None = None,
) -> JobResult:
    """Build the scene ``spec`` asks of ``volume`` (and ``label_map``), encode it in every
    format of ``spec.outputs`` and measure its error meanwhile; ``progress(stage, 0..1)``
    hears each stage.

    With a ``sink``, each file goes to ``sink.put`` as soon as it is encoded, GLB first
    (a viewer can draw the model while the rest is written and the error measured), and a
    sink that asks for a preview gets a coarse GLB (``put("preview", ...)``) before the
    model is built. ``export_options`` maps a format to its writer's options, e.g.
    ``{"glb": {"compress": True}}`` (the server sends meshopt-compressed glTF).
    ``measure=False`` leaves the error unmeasured (None in the report). ``blocks`` runs
    the threshold surfaces block by block (on Dask when it names a scheduler); volumes
    on disk (Zarr) and in memory over the budget (``MISS_IN_MEMORY_MAX_MB``) always are,
    and their progress counts blocks.
    """
    report = staged(progress or _no_progress)
    seconds: dict[str, float] = {}
    if sink is not None and sink.wants_preview:
        start = time.perf_counter()
        report("preview", 0.0)
        data = preview(volume, spec, label_map=label_map, table=table, title=title)
        if data is not None:
            sink.put(PREVIEW, data)
            seconds["preview"] = time.perf_counter() - start
    report("surface", 0.0)
    if in_blocks(volume, blocks):
        blocks = replace(blocks or BlockRun(), progress=report)
    built = build_scene(
        volume, spec, label_map=label_map, table=table, title=title, measure=False,
        blocks=blocks, measure_later=measure, progress=report, ordered=False,
    )  # fmt: skip
    seconds |= built.seconds
    built, spent = _tiled_then_ordered(built, sink, title, metadata, report)
    seconds |= spent
    start = time.perf_counter()
    artifacts: dict[str, bytes] = {}
    formats = sorted(spec.outputs.formats, key=lambda f: f != "glb")  # what viewers load first
    # The error is measured on a second thread once the first file is out, while the others
    # are written (the measurement's kernels run without the GIL): a job is done sooner.
    # The sink keeps the scene on a thread of its own meanwhile (zlib leaves the GIL too).
    with (
        ThreadPoolExecutor(max_workers=1, thread_name_prefix="miss-measure") as pool,
        ThreadPoolExecutor(max_workers=1, thread_name_prefix="miss-keep") as keeper,
    ):
        keeping = keeper.submit(_keep_scene, sink, built.scene, title, metadata)
        measuring: Future[SceneBuild] | None = None
        for i, fmt in enumerate(formats):
            report("write", i / len(formats))
            options = _writer_options(export_options, fmt)
            artifacts[fmt] = export(built.scene, fmt, title=title, metadata=metadata, **options)
            if sink is not None:
                sink.put(fmt, artifacts[fmt])
                if fmt == "glb" and "lod" not in seconds:
                    seconds |= _viewer_turn(sink)
                    start += seconds.get("viewer", 0.0)  # waiting is not writing
            if measure:
                measuring = measuring or pool.submit(built.measured)
        seconds["write"] = time.perf_counter() - start
        seconds |= keeping.result()
        if measuring is not None:
            report("measure", 0.0)
            built = measuring.result()
            seconds["measure"] = built.seconds.get("measure", 0.0)
    report("done", 1.0)
    artifacts = {fmt: artifacts[fmt] for fmt in spec.outputs.formats}  # in the asked order
    report_ = combined_report(built.reports)
    return JobResult(built.scene, report_, artifacts, seconds, dict(metadata or {}), title)


def _writer_options(export_options: ExportOptions | None, fmt: str) -> dict[str, Any]:
    """The options ``fmt``'s writer gets: the caller's, and for the GLB that the built
    scene is in :func:`~miss.geometry.locality_order` already (not reordered again)."""
    options = dict((export_options or {}).get(fmt, {}))
    return options | {"ordered": True} if fmt == "glb" else options


#: The name a sink gets a job's preview under (a coarse GLB, before the model).
PREVIEW = "preview"
#: A region of fewer voxels than this gets no preview: its model comes about as fast.
PREVIEW_MIN_VOXELS = 2_000_000
#: About as many voxels as a preview reads (its step along each axis, times the job's,
#: is the cube root of the region's share), and the least it decimates: some 40 ms of
#: work whatever the volume's size (CThead, 7.4 M voxels: every third voxel).
PREVIEW_VOXELS, PREVIEW_REDUCE = 600_000, 0.9


def preview(
    volume: Volume,
    spec: JobSpec,
    *,
    label_map: Volume | None = None,
    table: TableSpec = None,
    title: str | None = None,
) -> bytes | None:
    """A coarse, compressed GLB of the job's scene, for a viewer to draw within a second:
    every n-th voxel of the job's sampling (about :data:`PREVIEW_VOXELS` in all),
    quadric-decimated, nothing measured. None when the region is small (its model is
    nearly as quick) or has no surface that coarse.
    """
    box = spec.region.box(volume.dims)
    voxels = math.prod(
        (hi - lo) // s + 1 for (lo, hi), s in zip(box, spec.region.steps, strict=True)
    )
    if voxels < PREVIEW_MIN_VOXELS:
        return None
    step = max(2, math.ceil((voxels / PREVIEW_VOXELS) ** (1 / 3)))
    coarse = replace(
        spec,
        region=replace(spec.region, sample_rate=tuple(s * step for s in spec.region.steps)),
        decimation=replace(
            spec.decimation,
            method="quadric",
            reduce=max(spec.decimation.reduce, PREVIEW_REDUCE),
            schedule="paper",  # a coarse preview, replaced in a second: no bound is promised
        ),
    )
    try:
        built = build_scene(
            volume, coarse, label_map=label_map, table=table, title=title, measure=False
        )
    except EmptySurface:  # thin structures may vanish at a coarse resolution
        return None
    return export(built.scene, "glb", title=title, compress=True, ordered=True)


def _tiled_then_ordered(
    built: SceneBuild,
    sink: Sink | None,
    title: str | None,
    metadata: dict[str, str] | None,
    report: Progress,
) -> tuple[SceneBuild, dict[str, float]]:
    """The levels of detail a sink takes (a viewer draws them rather than a GLB too large
    to draw), then the scene laid out for its files (:func:`ordered_scene`; the tiles lay
    out their own, so a viewer has them sooner); the build and the seconds each took."""
    seconds: dict[str, float] = {}
    if sink is not None:
        seconds |= _levels_of_detail(built.scene, sink, title, metadata, report)
        if "lod" in seconds:
            seconds |= _viewer_turn(sink)
    start = time.perf_counter()
    built = replace(built, scene=ordered_scene(built.scene))
    return built, seconds | {"order": time.perf_counter() - start}


def _levels_of_detail(
    scene: Scene,
    sink: Sink,
    title: str | None,
    metadata: dict[str, str] | None,
    report: Progress = _no_progress,
) -> dict[str, float]:
    """A scene over the sink's ``lod_triangles`` goes to ``sink.put_lod`` as a 3D Tiles
    tileset too, before any file (a viewer draws its coarse root at once, never the whole
    GLB); returns the seconds it took, none when the scene is within the budget."""
    budget = getattr(sink, "lod_triangles", None)  # sinks that predate levels of detail
    if budget is None or scene.n_triangles <= budget:
        return {}
    from miss.export.tiles import write_tiles

    report("lod", 0.0)
    start = time.perf_counter()
    tile_triangles = min(LOD_TILE_MAX, max(LOD_TILE_MIN, budget // 8))
    sink.put_lod(write_tiles(scene, title=title, metadata=metadata, tile_triangles=tile_triangles))
    return {"lod": time.perf_counter() - start}


def _viewer_turn(sink: Sink) -> dict[str, float]:
    """The sink's ``wait_for_viewer`` (sinks that have none go on at once), as seconds
    ``viewer`` when it waited."""
    wait = getattr(sink, "wait_for_viewer", None)
    waited = wait() if wait is not None else 0.0
    return {"viewer": waited} if waited > 0 else {}


def _keep_scene(
    sink: Sink | None, scene: Scene, title: str | None, metadata: dict[str, str] | None
) -> dict[str, float]:
    """The sink's ``keep_scene`` (if it has one) given the scene; the seconds it took."""
    keep = getattr(sink, "keep_scene", None)
    if keep is None:
        return {}
    start = time.perf_counter()
    keep(scene, title, dict(metadata or {}))
    return {"keep": time.perf_counter() - start}


#: A tile holds an eighth of the budget's triangles, within these bounds.
LOD_TILE_MIN, LOD_TILE_MAX = 4096, 65_536


class Sink(Protocol):
    """Where a job's files go: ``put`` gets each one once it is encoded (GLB first; a
    ``preview`` before the model when ``wants_preview``), ``deliver`` the finished result
    (every file put, the error measured). A scene of more than ``lod_triangles`` (None:
    never) also goes to ``put_lod`` as levels of detail ({name: bytes}, one tileset).
    A sink may also have ``wait_for_viewer() -> seconds``, called once what a viewer
    draws (the levels of detail, else the GLB) is put, before the other files and the
    error: the server's waits while a viewer draws the model on the same machine
    (:mod:`miss.server.jobs.turn`); and ``keep_scene(scene, title, metadata)``, called on
    a thread of its own while the files are written: the server keeps the scene, from
    which it makes the other formats when they are asked for."""

    # read-only: the pipeline reads them, and a sink may fix them on its class
    @property
    def wants_preview(self) -> bool:
        """True when a coarse ``preview`` GLB is wanted before the model."""

    @property
    def lod_triangles(self) -> int | None:
        """Past this many triangles the scene also goes to ``put_lod``; None: never."""

    def put(self, fmt: str, data: bytes) -> None:
        """Take one encoded file, of format ``fmt``."""

    def put_lod(self, files: Mapping[str, bytes]) -> None:
        """Take the levels of detail, {name: bytes}, one tileset."""

    def deliver(self, result: JobResult) -> Any:
        """Take the finished result (every file put, the error measured)."""


@dataclass(frozen=True)
class Files:
    """Each format to its path (``miss convert -o``), written atomically: a temporary
    file beside it, renamed, so no half-written file is left behind."""

    paths: Mapping[str, tuple[Path, ...]]
    wants_preview = False
    lod_triangles = None

    def put_lod(self, files: Mapping[str, bytes]) -> None:
        """Levels of detail are not written to files."""
        return None

    def put(self, fmt: str, data: bytes) -> None:
        """Write ``data`` to each path of format ``fmt``."""
        for path in self.paths.get(fmt, ()):
            write_atomic(path, data)

    def deliver(self, result: JobResult) -> list[dict[str, Any]]:
        """Each file written, with its size in bytes."""
        return [
            {"path": str(path), "bytes": path.stat().st_size}
            for paths in self.paths.values()
            for path in paths
        ]


def write_atomic(path: Path, data: bytes) -> None:
    """Write to ``.<name>.part`` beside ``path`` and rename it into place."""
    tmp = path.with_name(f".{path.name}.part")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def provenance(spec: JobSpec, extra: Mapping[str, str] | None = None) -> dict[str, str]:
    """What a model file says about where it came from: software, the job's form and what
    the source adds (strings only; never a patient's name, ID or original UID)."""
    from miss import __version__

    params = {k: v for k, v in spec.to_dict().items() if k != "formats"}
    return {
        "software": f"MISS {__version__}",
        "parameters": json.dumps(params, sort_keys=True),
        **(extra or {}),
    }


def execute(
    spec: JobSpec,
    sink: Sink,
    progress: Progress | None = None,
    *,
    export_options: ExportOptions | None = None,
    measure: bool = True,
    blocks: BlockRun | None = None,
) -> tuple[JobResult, Any]:
    """Load ``spec.source``, run the job, deliver the files: (result, what the sink said).

    ``result.seconds`` starts with ``read`` (loading the source) and ends with
    ``total``.
    """
    if spec.source is None:
        raise BadParameter("the job has no source: say which volume to read.")
    start = time.perf_counter()
    measurer.prestart(spec, measure)  # its numba starts while the volume is read
    (progress or _no_progress)("read", 0.0)
    loaded = spec.source.load(labels=spec.structures.labels_used is not None)
    read = time.perf_counter() - start
    result = run(
        loaded.volume, spec, progress, title=loaded.title,
        metadata=provenance(spec, loaded.provenance), label_map=loaded.label_map,
        table=loaded.table, export_options=export_options, sink=sink, measure=measure,
        blocks=blocks,
    )  # fmt: skip
    delivered = sink.deliver(result)
    result.seconds = {"read": read, **result.seconds, "total": time.perf_counter() - start}
    return result, delivered
