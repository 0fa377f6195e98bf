"""The job as data: a frozen ``JobSpec`` and ``run(volume, spec) -> JobResult``.

No web, no globals: the CLI and the server's workers both call ``run``.
"""

from __future__ import annotations

import hashlib
import json
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields
from typing import Any

from miss.decimate import METHODS, DecimationReport, decimate
from miss.errors import BadParameter
from miss.export import WRITERS, export
from miss.labels import TableSpec
from miss.scene import Scene
from miss.structures import SceneOptions, build_scene, combined_report
from miss.surface import extract_surface
from miss.types import Mesh, Volume

Progress = Callable[[str, float], None]


def _no_progress(stage: str, fraction: float) -> None:
    return None


@dataclass(frozen=True)
class JobSpec:
    """The paper's processing choices (the 1998 web form), validated on construction.

    ``level`` is in the volume's real units (HU for CT); slices are 1-based and
    inclusive along the third voxel axis; bounds are fractions of the diagonal.
    The fields after ``formats`` make a scene job (several structures, see
    :func:`miss.extract_scene`); ``level`` may then be left out.
    """

    level: float | None = None
    sample_rate: int | tuple[int, int, int] = 1
    start_slice: int | None = None
    end_slice: int | None = None
    roi: tuple[int, int, int, int, int, int] | None = None
    decimate: str = "quadric"
    error_bound: float = 0.0002
    reduce: float = 0.9
    max_error: float = 0.01
    formats: tuple[str, ...] = field(default=("glb",))
    # Structures; at these defaults a job and its key() are what they were before them.
    levels: tuple[float, ...] | None = None
    labels: str | tuple[int, ...] | None = None
    components: str = "all"
    min_size_mm3: float = 0.0
    smooth: int | None = None
    passband: float = 0.1

    def __post_init__(self) -> None:
        _validate(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> JobSpec:
        """Build from JSON-like data; unknown keys and wrong types raise ``BadParameter``."""
        names = {f.name for f in fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise BadParameter(
                f"unknown job parameter(s) {sorted(unknown)}; known: {sorted(names)}."
            )
        if "level" not in data and not data.get("levels") and data.get("labels") is None:
            raise BadParameter(
                "a job needs a 'level' (threshold in the volume's units, e.g. HU), "
                "'levels' or 'labels'."
            )
        values = dict(data)
        for key in ("sample_rate", "roi", "formats", "levels", "labels"):
            if isinstance(values.get(key), list):
                values[key] = tuple(values[key])
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def key(self) -> str:
        """Stable hash of the parameters that shape the surface (not the output formats)."""
        d = self.to_dict()
        d.pop("formats")
        d["sample_rate"] = list(self.steps)
        for name, default in _STRUCTURE_DEFAULTS.items():
            if d[name] == default:
                del d[name]  # old specs keep their keys (and cached results)
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:32]

    @property
    def steps(self) -> tuple[int, int, int]:
        sr = self.sample_rate
        return (sr, sr, sr) if isinstance(sr, int) else (sr[0], sr[1], sr[2])

    @property
    def is_scene(self) -> bool:
        """True when the job asks for structures (a scene), not one surface."""
        return any(getattr(self, name) != d for name, d in _STRUCTURE_DEFAULTS.items())

    def scene_options(self, volume: Volume) -> SceneOptions:
        """The :class:`~miss.structures.SceneOptions` this spec means for ``volume``."""
        levels = self.levels or (() if self.level is None else (self.level,))
        return SceneOptions(
            levels=tuple(levels), labels=self.labels, components=self.components,
            min_size_mm3=self.min_size_mm3, smooth=self.smooth, passband=self.passband,
            decimate=self.decimate, reduce=self.reduce, error_bound=self.error_bound,
            max_error=self.max_error, sample_rate=self.sample_rate,
            slices=slice_range(self, volume), roi=self.roi,
        )  # fmt: skip


#: The structure fields and their defaults (a plain single-level job).
_STRUCTURE_DEFAULTS: dict[str, Any] = {
    "levels": None,
    "labels": None,
    "components": "all",
    "min_size_mm3": 0.0,
    "smooth": None,
    "passband": 0.1,
}


def _is_int(x: Any) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_num(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def _validate(spec: JobSpec) -> None:
    if spec.level is None and not spec.levels and spec.labels is None:
        raise BadParameter("a job needs a 'level' (threshold in the volume's units, e.g. HU).")
    if spec.level is not None and not _is_num(spec.level):
        raise BadParameter(f"level must be a number in the volume's units, got {spec.level!r}.")
    sr = spec.sample_rate
    ok = _is_int(sr) or (isinstance(sr, tuple) and len(sr) == 3 and all(_is_int(s) for s in sr))
    if not ok or min(spec.steps) < 1:
        raise BadParameter(f"sample_rate must be an integer >= 1 or three of them, got {sr!r}.")
    for name in ("start_slice", "end_slice"):
        value = getattr(spec, name)
        if value is not None and (not _is_int(value) or value < 1):
            raise BadParameter(f"{name} must be a whole number >= 1 (1-based), got {value!r}.")
    if spec.start_slice and spec.end_slice and spec.start_slice > spec.end_slice:
        raise BadParameter(
            f"start_slice {spec.start_slice} is after end_slice {spec.end_slice}; swap them."
        )
    if spec.decimate not in METHODS:
        raise BadParameter(f"decimate must be one of {', '.join(METHODS)}, got {spec.decimate!r}.")
    for name in ("error_bound", "reduce", "max_error"):
        if not _is_num(getattr(spec, name)):
            raise BadParameter(f"{name} must be a number, got {getattr(spec, name)!r}.")
    if not 0.0 <= spec.reduce < 1.0:
        raise BadParameter(
            f"reduce must be in [0, 1) (fraction removed, e.g. 0.9), got {spec.reduce!r}."
        )
    if not 0.0 < spec.error_bound <= spec.max_error:
        raise BadParameter(
            f"error_bound must be > 0 and <= max_error {spec.max_error!r}, got {spec.error_bound!r}."
        )
    bad = [f for f in spec.formats if f.lower().lstrip(".") not in WRITERS]
    if bad or not spec.formats:
        raise BadParameter(f"unknown output format(s) {bad}; choose from {', '.join(WRITERS)}.")
    if spec.is_scene:
        _validate_structures(spec)


def _validate_structures(spec: JobSpec) -> None:
    """The structure fields, checked as :class:`SceneOptions` checks them."""
    if spec.levels is not None and not all(_is_num(v) for v in spec.levels):
        raise BadParameter(f"levels must be numbers in the volume's units, got {spec.levels!r}.")
    if spec.smooth is not None and not _is_int(spec.smooth):
        raise BadParameter(f"smooth must be a whole number of iterations, got {spec.smooth!r}.")
    if not _is_num(spec.min_size_mm3) or not _is_num(spec.passband):
        raise BadParameter("min_size_mm3 and passband must be numbers.")
    SceneOptions(
        levels=spec.levels or (), labels=spec.labels, components=spec.components,
        min_size_mm3=spec.min_size_mm3, smooth=spec.smooth, passband=spec.passband,
    )  # fmt: skip


@dataclass
class JobResult:
    """Surface, decimation report, encoded files and per-stage seconds of one run."""

    mesh: Mesh
    report: DecimationReport
    artifacts: dict[str, bytes]
    seconds: dict[str, float]
    scene: Scene | None = None  # set for a scene job; ``mesh`` then holds all parts merged

    def stats(self) -> dict[str, Any]:
        if self.scene is not None:
            return {
                **self._mesh_stats(),
                "parts": self.scene.summary(),
                "notes": list(self.scene.notes),
            }
        return self._mesh_stats()

    def _mesh_stats(self) -> dict[str, Any]:
        return {
            "triangles": self.mesh.n_triangles,
            "vertices": self.mesh.n_vertices,
            "seconds": self.seconds,
            "bytes": {fmt: len(data) for fmt, data in self.artifacts.items()},
            "decimation": {
                "method": self.report.method,
                "reduce": self.report.reduce,
                "error_bound": self.report.error_bound,
                "triangles_before": self.report.triangles_in,
                "achieved_reduction": self.report.achieved_reduction,
                "max_error_mm": self.report.max_error_mm,
                "mean_error_mm": self.report.mean_error_mm,
            },
        }


def slice_range(spec: JobSpec, volume: Volume) -> tuple[int, int] | None:
    """The spec's 1-based inclusive slice range, with a missing end filled from the volume."""
    if spec.start_slice is None and spec.end_slice is None:
        return None
    return (spec.start_slice or 1, spec.end_slice or volume.dims[2])


ExportOptions = Mapping[str, Mapping[str, Any]]


@dataclass(frozen=True)
class _Encoder:
    """Writes a mesh or scene in every format of the spec, with progress and timing."""

    spec: JobSpec
    title: str | None
    metadata: dict[str, str] | None
    options: ExportOptions

    def __call__(self, model: Mesh | Scene, progress: Progress) -> tuple[dict[str, bytes], float]:
        start = time.perf_counter()
        artifacts: dict[str, bytes] = {}
        for i, fmt in enumerate(self.spec.formats):
            progress("write", 0.7 + 0.3 * i / len(self.spec.formats))
            key = fmt.lower().lstrip(".")
            artifacts[key] = export(
                model, key, title=self.title, metadata=self.metadata, **self.options.get(key, {})
            )
        return artifacts, time.perf_counter() - start


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
) -> JobResult:
    """Surface, decimate and encode ``volume`` as ``spec`` says; ``progress(stage, 0..1)``.

    A scene job (``spec.is_scene``, or a ``label_map`` laid over the volume) builds
    a :class:`~miss.scene.Scene` instead, names and colours from ``table``.
    ``export_options`` maps a format to its writer's options, e.g.
    ``{"glb": {"compress": True}}`` (the server sends meshopt-compressed glTF).
    """
    encode = _Encoder(spec, title, metadata, export_options or {})
    if spec.is_scene or label_map is not None:
        return _run_scene(volume, spec, progress or _no_progress, encode, label_map, table)
    report_progress = progress or _no_progress
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    report_progress("surface", 0.0)
    mesh = extract_surface(
        volume,
        spec.level,
        spec.steps,
        slice_range(spec, volume),
        spec.roi,
        normals=spec.decimate == "none",  # a decimated mesh gets new normals from its faces
    )
    seconds["surface"] = time.perf_counter() - t0
    report_progress("decimate", 0.35)
    t1 = time.perf_counter()
    mesh, report = decimate(
        mesh, spec.decimate, spec.reduce, spec.error_bound, max_error=spec.max_error
    )
    seconds["decimate"] = time.perf_counter() - t1
    artifacts, seconds["write"] = encode(mesh, report_progress)
    report_progress("done", 1.0)
    return JobResult(mesh=mesh, report=report, artifacts=artifacts, seconds=seconds)


def _run_scene(
    volume: Volume,
    spec: JobSpec,
    report_progress: Progress,
    encode: _Encoder,
    label_map: Volume | None,
    table: TableSpec,
) -> JobResult:
    """The structures of ``volume`` (and ``label_map``) as one scene, encoded."""
    report_progress("surface", 0.0)
    built = build_scene(
        volume, spec.scene_options(volume), label_map=label_map, table=table, title=encode.title
    )
    seconds = dict(built.seconds)
    artifacts, seconds["write"] = encode(built.scene, report_progress)
    report_progress("done", 1.0)
    return JobResult(
        mesh=built.scene.merged(),
        report=combined_report(built.reports),
        artifacts=artifacts,
        seconds=seconds,
        scene=built.scene,
    )
