"""The job run: ``run(volume, spec) -> JobResult`` and ``execute(spec, sink)``.

``execute`` is the one path every job takes, from ``miss convert`` and from the
server's workers alike: the spec's source loads the volume, :func:`run` builds the
scene (one level is a scene of one part) and encodes it, and a :class:`Sink` delivers
the files (to paths on the command line, to the data folder in the server; back to a
PACS next). No web, no globals.
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Protocol

from miss.decimate import DecimationReport
from miss.errors import BadParameter
from miss.export import export
from miss.scene import Scene
from miss.spec import JobSpec
from miss.structures.build import build_scene, combined_report
from miss.structures.labels import TableSpec
from miss.types import Mesh, Volume

Progress = Callable[[str, float], None]
#: A format's writer options, e.g. ``{"glb": {"compress": True}}``.
ExportOptions = Mapping[str, Mapping[str, Any]]


def _no_progress(stage: str, fraction: float) -> None:
    return None


@dataclass
class JobResult:
    """The scene, its decimation report (all parts together), the encoded files and the
    seconds each stage took."""

    scene: Scene
    report: DecimationReport
    artifacts: dict[str, bytes]
    seconds: dict[str, float]
    metadata: dict[str, str] = field(default_factory=dict)  # provenance in the files

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
) -> JobResult:
    """Build the scene ``spec`` asks of ``volume`` (and ``label_map``), then encode it in
    every format of ``spec.outputs``; ``progress(stage, 0..1)`` hears each stage.

    ``export_options`` maps a format to its writer's options, e.g.
    ``{"glb": {"compress": True}}`` (the server sends meshopt-compressed glTF).
    """
    report = progress or _no_progress
    report("surface", 0.0)
    built = build_scene(volume, spec, label_map=label_map, table=table, title=title)
    seconds = dict(built.seconds)
    start = time.perf_counter()
    artifacts: dict[str, bytes] = {}
    formats = spec.outputs.formats
    for i, fmt in enumerate(formats):
        report("write", 0.7 + 0.3 * i / len(formats))
        options = (export_options or {}).get(fmt, {})
        artifacts[fmt] = export(built.scene, fmt, title=title, metadata=metadata, **options)
    seconds["write"] = time.perf_counter() - start
    report("done", 1.0)
    report_ = combined_report(built.reports)
    return JobResult(built.scene, report_, artifacts, seconds, dict(metadata or {}))


class Sink(Protocol):
    """Where a job's files go: ``deliver`` gets the finished result once."""

    def deliver(self, result: JobResult) -> Any: ...


@dataclass(frozen=True)
class Files:
    """Each format to its path (``miss convert -o``), written atomically: a temporary
    file beside it, renamed, so no half-written file is left behind."""

    paths: Mapping[str, tuple[Path, ...]]

    def deliver(self, result: JobResult) -> list[dict[str, Any]]:
        written = []
        for fmt, paths in self.paths.items():
            for path in paths:
                write_atomic(path, result.artifacts[fmt])
                written.append({"path": str(path), "bytes": path.stat().st_size})
        return written


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
) -> tuple[JobResult, Any]:
    """Load ``spec.source``, run the job, deliver the files: (result, what the sink said).

    ``result.seconds`` starts with ``read`` (loading the source) and ends with
    ``total``.
    """
    if spec.source is None:
        raise BadParameter("the job has no source: say which volume to read.")
    start = time.perf_counter()
    (progress or _no_progress)("read", 0.0)
    loaded = spec.source.load(labels=spec.structures.labels_used is not None)
    read = time.perf_counter() - start
    result = run(
        loaded.volume, spec, progress, title=loaded.title,
        metadata=provenance(spec, loaded.provenance), label_map=loaded.label_map,
        table=loaded.table, export_options=export_options,
    )  # fmt: skip
    delivered = sink.deliver(result)
    result.seconds = {"read": read, **result.seconds, "total": time.perf_counter() - start}
    return result, delivered
