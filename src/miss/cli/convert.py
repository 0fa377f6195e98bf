"""``miss convert``: a volume to surface models, through the one job path
(:func:`miss.pipeline.execute`) the server's workers take too."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from miss.cli.options import add_job_options, add_source_options, job_form, source_of, whole_numbers


def add_arguments(conv: argparse.ArgumentParser) -> None:
    """``miss convert``: the source, the job's options and the output files."""
    add_source_options(conv)
    conv.add_argument(
        "-o", "--output", action="append", required=True, metavar="OUT",
        help="output file; format from its extension (.plain.glb: a GLB without "
        "compression or extensions); repeat for several",
    )  # fmt: skip
    conv.add_argument("--json", action="store_true", help="print the run's statistics as JSON")
    conv.add_argument(
        "--measure", action="store_true",
        help="measure the decimated surface's deviation from the undecimated one, mm, "
        "with --schedule paper (numba's start, about a second, runs in a second process "
        "meanwhile); the default "
        "schedule, guaranteed, always measures: a bound is held only if it is checked",
    )  # fmt: skip
    run = conv.add_argument_group("run", "where the surfaces are computed (not part of the job)")
    run.add_argument(
        "--chunks", type=_chunks, default=None, metavar="N|X,Y,Z|auto",
        help="compute the surfaces block by block, N voxels a block edge (auto: 128); "
        "volumes on disk (Zarr) always are, and so are volumes of more voxels than "
        "$MISS_IN_MEMORY_MAX_MB (default 256 MB), read to a temporary chunked array on disk "
        "(in $TMPDIR) as they are read, never whole",
    )  # fmt: skip
    run.add_argument(
        "--scheduler", default=None, metavar="ADDRESS",
        help="run the blocks on this Dask cluster, e.g. tcp://host:8786 (default: "
        "$MISS_DASK_SCHEDULER; else this machine); its workers must reach the files by path",
    )  # fmt: skip
    add_job_options(conv)


def _chunks(text: str) -> str | int | tuple[int, ...]:
    """``auto``, ``N`` or ``X,Y,Z`` (blockwise checks the numbers)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        return whole_numbers(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(
            f"expected auto, N or X,Y,Z voxels, got {text!r}"
        ) from None


def _blocks(args: argparse.Namespace) -> Any:
    """The BlockRun the options ask for, or None (the job decides from its volume)."""
    import os

    from miss.surface.blockwise import BlockRun
    from miss.surface.runner import SCHEDULER_ENV

    if args.chunks is None and args.scheduler is None and not os.environ.get(SCHEDULER_ENV):
        return None
    block = None if args.chunks in (None, "auto") else args.chunks
    return BlockRun(block=block, scheduler=args.scheduler)


class _Bar:
    """A one-line progress bar on stderr, drawn only when stderr is a terminal."""

    def __init__(self) -> None:
        self.enabled = sys.stderr.isatty()

    def __call__(self, stage: str, fraction: float) -> None:
        if self.enabled:
            filled = int(30 * fraction)
            sys.stderr.write(f"\r{stage:<9} [{'#' * filled}{'.' * (30 - filled)}] {fraction:4.0%}")
            sys.stderr.flush()
            if fraction >= 1.0:
                sys.stderr.write("\n")


def _outputs(names: list[str]) -> dict[str, tuple[Path, ...]]:
    """Each format and the paths it goes to; refuses unknown extensions and folders."""
    from miss.errors import UnsupportedFormat
    from miss.export import WRITERS

    paths: dict[str, list[Path]] = {}
    for name in names:
        out = Path(name)
        # "head.plain.glb" is the plain GLB; "head.v2.stl" is still an STL.
        two = "".join(out.suffixes[-2:]).lower().lstrip(".")
        fmt = two if two in WRITERS else "".join(out.suffixes[-1:]).lower().lstrip(".")
        if fmt not in WRITERS:
            raise UnsupportedFormat(
                f"{out}: unknown output extension {out.suffix or '(none)'}; use one of "
                + ", ".join(f".{k}" for k in WRITERS)
            )
        if not out.parent.is_dir():
            raise UnsupportedFormat(f"{out}: folder {out.parent} does not exist; create it first.")
        paths.setdefault(fmt, []).append(out)
    return {fmt: tuple(p) for fmt, p in paths.items()}


def cmd_convert(args: argparse.Namespace) -> int:
    """Run one job from the command line and write its files; the exit status."""
    from miss.spec import JobSpec

    paths = _outputs(args.output)
    form = job_form(args)
    if not any(k in form for k in ("level", "levels", "labels", "parts")) or (
        args.label_map and "labels" not in form
    ):
        form["labels"] = "all"  # a label map's labels; a scan is refused, naming --level
    spec = JobSpec.from_dict({**form, "formats": list(paths)}, source_of(args))
    from miss.measure.measurer import prestart

    prestart(spec, args.measure)  # before VTK loads here: see miss.measure.measurer
    from miss.pipeline import Files, execute

    result, written = execute(
        spec, Files(paths), _Bar(), measure=args.measure, blocks=_blocks(args)
    )
    summary = {
        **result.stats(),
        "seconds": {k: round(v, 4) for k, v in result.seconds.items()},
        "outputs": written,
    }
    summary.pop("bytes")
    if args.json:
        print(json.dumps(summary))
    else:
        _print(summary)
    return 0


def _print(summary: dict[str, Any]) -> None:
    """Parts (when several), triangles, error, seconds, files written, notes."""
    parts = summary["parts"]
    if len(parts) > 1 or parts[0]["label"] is not None:
        for part in parts:
            label = "" if part["label"] is None else f"label {part['label']:<4} "
            print(f"part      {label}{part['name']:<28} {part['triangles']:>8} triangles "
                  f"{part['volume_ml']:>10.2f} mL {part['area_cm2']:>10.2f} cm²")  # fmt: skip
    d = summary["decimation"]
    error = (
        "error not measured: add --measure"
        if d["max_error_mm"] is None
        else f"max error {d['max_error_mm']:.3f} mm, mean {d['mean_error_mm']:.4f} mm"
    )
    if d.get("bound_held"):
        error += f" within the bound {d['bound_mm']:.3f} mm; stopped by {d['stopped_by']}"
    # the method that made the model (a held bound is schroeder's, whatever was asked for)
    method = d["finished_with"]
    print(
        f"{summary['triangles']} triangles, {summary['vertices']} vertices in {len(parts)} "
        f"part(s) ({d['triangles_before']} before {method} decimation; {error})"
    )
    print("seconds   " + "  ".join(f"{k} {v:.2f}" for k, v in summary["seconds"].items()))
    for o in summary["outputs"]:
        print(f"wrote     {o['path']} ({o['bytes'] / 1024:.0f} KB)")
    for note in summary["notes"]:
        print(f"note      {note}")
