"""``miss info``: what a volume is, and the labels of a label map with their names."""

from __future__ import annotations

import argparse
import json
from typing import Any


def add_arguments(info: argparse.ArgumentParser) -> None:
    """``miss info``: the volume (path and series) and ``--json``."""
    from miss.cli.options import add_source_options

    add_source_options(info, "path", "series")
    info.add_argument("--json", action="store_true", help="print one JSON object")


def describe(volume: Any) -> dict[str, Any]:
    """A volume's dimensions, spacing (mm), affine, value type and range, and metadata,
    as JSON values."""
    import numpy as np

    lo, hi = volume.value_range()
    return {
        "dims": list(volume.dims),
        "spacing": [round(s, 6) for s in volume.spacing],
        "affine": np.round(volume.affine, 6).tolist(),
        "dtype": str(volume.data.dtype),
        "range": [lo, hi],
        "modality": volume.meta.get("modality", ""),
        "units": volume.meta.get("units", ""),
        "series": volume.meta.get("series", []),
        "notes": volume.meta.get("notes", []),
    }


def cmd_info(args: argparse.Namespace) -> int:
    """Print what a volume holds, as text or JSON; the exit status."""
    from miss.io import load_volume

    volume = load_volume(args.path, series=args.series)
    desc = {**describe(volume), **label_listing(volume, args.path)}
    if args.json:
        print(json.dumps(desc))
        return 0
    print(f"dims      {' x '.join(map(str, desc['dims']))} (columns x rows x slices)")
    print(f"spacing   {' x '.join(f'{s:g}' for s in desc['spacing'])} mm")
    print(
        f"values    {desc['range'][0]:g} .. {desc['range'][1]:g} {desc['units']} ({desc['dtype']})"
    )
    print(f"modality  {desc['modality'] or '-'}")
    for s in desc["series"]:
        print(f"series    {s.get('uid')}  {s.get('slices')} slices  {s.get('description', '')}")
    for note in desc["notes"]:
        print(f"note      {note}")
    labels = desc.get("labels", [])
    if len(labels) > LISTED and desc.get("label_table") is None:
        # an 8-bit image (a windowed CT, a scout) passes for a label map of every value it
        # holds: a line for each of them tells the reader nothing
        print(
            f"labels    {len(labels)} values besides 0 ({labels[0]['label']} .. "
            f"{labels[-1]['label']}), none named: an image, or a label map of that many "
            "labels (--json lists each)"
        )
        return 0
    for item in labels:
        print(f"label     {item['label']:<5} {item['voxels']:>10} voxels  {item['name'] or ''}")
    return 0


#: More labels than this, none of them named, are summed up in one line, not listed.
LISTED = 64


def label_listing(volume: Any, path: str) -> dict[str, Any]:
    """The labels of a label map with voxel counts, mL and known names.

    Empty for anything that is not a label map (float data, negative values, or
    more than :data:`miss.structures.counts.MAX_LABELS` distinct values).
    """
    import numpy as np

    from miss.structures.counts import label_counts
    from miss.structures.labels import find_label_table

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
