"""The command line's structure options: several levels, components, label maps.

Kept apart from :mod:`miss.cli` so that file stays a table of commands;
``miss convert`` hands over here when a scene is asked for, and ``miss info``
adds the label listing of a label map.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any


def add_structure_arguments(conv: argparse.ArgumentParser) -> None:
    """The ``convert`` options that make a scene of several named structures."""
    group = conv.add_argument_group("structures (a scene of named, coloured parts)")
    group.add_argument(
        "--labels",
        metavar="all|1,4,7",
        help="label map: build these labels, one part each (default for a label map: all)",
    )
    group.add_argument(
        "--label-map",
        metavar="SEG",
        help="a label map of the volume (e.g. TotalSegmentator output), laid over it in mm",
    )
    group.add_argument(
        "--label-table",
        metavar="auto|none|totalseg|FILE",
        default="auto",
        help="label names and colours: a 3D Slicer .ctbl/.txt or ITK-SNAP file; "
        "auto looks beside the label map and in its NIfTI header",
    )
    group.add_argument(
        "--components",
        choices=["all", "largest", "split"],
        default="all",
        help="keep every piece, the largest only, or one part per piece",
    )
    group.add_argument(
        "--min-size",
        type=float,
        default=0.0,
        metavar="MM3",
        help="leave out pieces smaller than this volume (mm³)",
    )
    group.add_argument(
        "--max-parts",
        type=int,
        default=100,
        metavar="N",
        help="with --components split, at most this many parts (largest first)",
    )
    group.add_argument(
        "--smooth",
        type=int,
        default=None,
        metavar="N",
        help="windowed-sinc smoothing iterations (default: 20 for labels, 0 for levels)",
    )
    group.add_argument("--passband", type=float, default=0.1,
                       help="smoothing passband in (0, 2); smaller smooths more")  # fmt: skip


def wants_scene(args: argparse.Namespace) -> bool:
    """Whether ``convert`` builds a scene rather than the one surface of one level."""
    levels = args.level or []
    return (
        len(levels) != 1
        or args.labels is not None
        or args.label_map is not None
        or args.components != "all"
        or args.min_size > 0
        or args.smooth is not None
    )


def convert_scene(args: argparse.Namespace, outputs: list[Path], formats: list[str]) -> int:
    """``miss convert`` for a scene: build, write every output, print a summary with parts."""
    from miss.cli import _Bar, _write_atomic
    from miss.io import load_volume
    from miss.pipeline import JobSpec, run

    t0 = time.perf_counter()
    volume = load_volume(args.path, series=args.series)
    label_map = load_volume(args.label_map) if args.label_map else None
    spec = JobSpec(
        levels=tuple(args.level) if args.level else None,
        labels=_labels(args, volume, label_map), components=args.components,
        min_size_mm3=args.min_size, smooth=args.smooth, passband=args.passband,
        sample_rate=args.sample_rate, start_slice=args.start_slice, end_slice=args.end_slice,
        decimate=args.decimate, error_bound=args.error_bound, reduce=args.reduce,
        formats=tuple(dict.fromkeys(formats)),
    )  # fmt: skip
    t_read = time.perf_counter() - t0
    result = run(
        volume, spec, progress=_Bar(), title=Path(args.path).name,
        metadata={"software": "MISS", "parameters": json.dumps(spec.to_dict())},
        label_map=label_map, table=_table(args),
    )  # fmt: skip
    for out, fmt in zip(outputs, formats, strict=True):
        _write_atomic(out, result.artifacts[fmt])
    seconds = {"read": t_read, **result.seconds, "total": time.perf_counter() - t0}
    _print_summary(result, outputs, seconds, args.json)
    return 0


def _labels(args: argparse.Namespace, volume: Any, label_map: Any) -> str | None:
    """``--labels``; "all" for a label map given without levels or labels; else refuse."""
    from miss.errors import BadParameter
    from miss.labelmap import label_counts

    if args.labels is not None or args.level:
        return args.labels
    if label_map is not None or label_counts(volume) is not None:
        return "all"
    raise BadParameter(
        "give --level (a threshold in the volume's units, HU for CT) or, for a label map, "
        "--labels all|1,4,7; this volume is not a label map."
    )


def _table(args: argparse.Namespace) -> Any:
    """The label-table choice, resolved against the file the labels come from."""
    from miss.labels import resolve_table

    return resolve_table(args.label_table, args.label_map or args.path)


def _print_summary(
    result: Any, outputs: list[Path], seconds: dict[str, float], as_json: bool
) -> None:
    """JSON (``--json``) or a short table: parts, triangles, mL, cm², outputs, notes."""
    report = result.report
    summary = {
        "parts": result.scene.summary(),
        "triangles": result.mesh.n_triangles,
        "vertices": result.mesh.n_vertices,
        "seconds": {k: round(v, 4) for k, v in seconds.items()},
        "outputs": [{"path": str(o), "bytes": o.stat().st_size} for o in outputs],
        "decimation": {
            "method": report.method, "reduce": report.reduce, "error_bound": report.error_bound,
            "achieved_reduction": round(report.achieved_reduction, 4),
            "triangles_before": report.triangles_in, "max_error_mm": report.max_error_mm,
            "mean_error_mm": report.mean_error_mm,
        },
        "notes": list(result.scene.notes),
    }  # fmt: skip
    if as_json:
        print(json.dumps(summary))
        return
    for part in summary["parts"]:
        label = "" if part["label"] is None else f"label {part['label']:<4} "
        print(f"part      {label}{part['name']:<28} {part['triangles']:>8} triangles "
              f"{part['volume_ml']:>10.2f} mL {part['area_cm2']:>10.2f} cm²")  # fmt: skip
    print(f"{summary['triangles']} triangles in {len(summary['parts'])} parts "
          f"({report.triangles_in} before {report.method} decimation)")  # fmt: skip
    print("seconds   " + "  ".join(f"{k} {v:.2f}" for k, v in summary["seconds"].items()))
    for o in summary["outputs"]:
        print(f"wrote     {o['path']} ({o['bytes'] / 1024:.0f} KB)")
    for note in summary["notes"]:
        print(f"note      {note}")


def label_listing(volume: Any, path: str) -> dict[str, Any]:
    """For ``miss info``: the labels of a label map with voxel counts, mL and known names.

    Empty for anything that is not a label map (float data, negative values, or
    more than :data:`miss.labelmap.MAX_LABELS` distinct values).
    """
    import numpy as np

    from miss.labelmap import label_counts
    from miss.labels import find_label_table

    counts = label_counts(volume)
    if counts is None:
        return {}
    found = find_label_table(path)
    table, source = found if found else ({}, None)
    voxel_ml = abs(float(np.linalg.det(volume.affine[:3, :3]))) / 1000.0
    labels = [
        {"label": label, "voxels": n, "volume_ml": round(n * voxel_ml, 4),
         "name": table[label].name if label in table else None}
        for label, n in sorted(counts.items())
    ]  # fmt: skip
    return {"labels": labels, "label_table": source}
