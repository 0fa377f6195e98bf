"""The ``miss`` command line: info, convert, demo, serve.

Bad input ends with one line on stderr naming the problem and the fix, exit code 2.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from miss.cli_scene import add_structure_arguments, convert_scene, label_listing, wants_scene

EXIT_BAD_INPUT = 2


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error on one line."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"miss: {message} (see 'miss {self.prog.split()[-1]} --help')\n")


def _sample_rate(text: str) -> int | tuple[int, int, int]:
    parts = text.split(",")
    try:
        values = [int(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"sample rate must be N or X,Y,Z integers, got {text!r}"
        ) from None
    if len(values) == 1:
        return values[0]
    if len(values) == 3:
        return values[0], values[1], values[2]
    raise argparse.ArgumentTypeError(f"sample rate must be N or X,Y,Z, got {text!r}")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="miss", description="MISS - CT/MRI volumes to shared 3-D surface models.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    info = sub.add_parser(
        "info", help="describe a volume (DICOM folder/zip, NIfTI, NRRD, MetaImage)"
    )
    info.add_argument("path")
    info.add_argument("--series", help="DICOM SeriesInstanceUID when the folder holds several")
    info.add_argument("--json", action="store_true", help="print one JSON object")

    conv = sub.add_parser("convert", help="volume -> surface model(s)")
    conv.add_argument("path")
    conv.add_argument(
        "-o",
        "--output",
        action="append",
        required=True,
        metavar="OUT",
        help="output file; format from its extension; repeat for several",
    )
    conv.add_argument(
        "--level", type=float, action="append", metavar="LEVEL",
        help="threshold in the volume's units (HU for CT); repeat for several structures",
    )  # fmt: skip
    conv.add_argument("--series")
    conv.add_argument("--sample-rate", type=_sample_rate, default=1, metavar="N|X,Y,Z")
    conv.add_argument(
        "--start-slice", type=int, metavar="A", help="1-based first slice (inclusive)"
    )
    conv.add_argument("--end-slice", type=int, metavar="B", help="1-based last slice (inclusive)")
    conv.add_argument("--decimate", default="quadric", choices=["none", "schroeder", "quadric"])
    conv.add_argument(
        "--error-bound",
        type=float,
        default=0.0002,
        help="local error bound, fraction of the bounding-box diagonal (paper: 0.0002, 0.002)",
    )
    conv.add_argument(
        "--reduce", type=float, default=0.9, help="target fraction of triangles removed"
    )
    conv.add_argument("--json", action="store_true", help="print the run's statistics as JSON")
    add_structure_arguments(conv)

    demo = sub.add_parser("demo", help="write the synthetic CT head phantom as NIfTI")
    demo.add_argument("output", help="e.g. demo-head.nii.gz")

    bench = sub.add_parser("bench", help="regenerate the 1998 paper's performance tables")
    bench.add_argument("suite", choices=["paper"], help="'paper': Tables 1-2 on the CThead volume")
    bench.add_argument(
        "--out", default="benchmarks/results", help="folder for JSON, Markdown and PNG"
    )
    bench.add_argument(
        "--repeats", type=int, default=5, help="timed runs per row (the median is kept)"
    )
    bench.add_argument("--volume", default=None, help="CThead.nhdr (default: ../shared/datasets)")
    bench.add_argument(
        "--sample-rates",
        default="1,2,4",
        metavar="A,B,...",
        help="sample rates to measure (default 1,2,4)",
    )

    serve = sub.add_parser("serve", help="start the web system")
    serve.add_argument("--host", default=None)
    serve.add_argument("--port", type=int, default=None)
    serve.add_argument("--data-dir", default=None)
    _add_account_commands(sub)
    return parser


def _add_account_commands(sub: Any) -> None:
    """``miss user add`` and ``miss audit``: the server's accounts and audit log, offline."""
    user = sub.add_parser("user", help="manage the web system's accounts")
    user_sub = user.add_subparsers(dest="user_command", required=True, parser_class=_Parser)
    add = user_sub.add_parser("add", help="create an account; the password is read from stdin")
    add.add_argument("name")
    add.add_argument("--admin", action="store_true", help="may see everything and read the audit")
    add.add_argument("--data-dir", default=None, help="default: MISS_DATA_DIR or ./miss-data")
    helps = {
        "passwd": "set an account's password (read from stdin); its logins end",
        "disable": "disable an account: it cannot log in, and its logins end",
        "enable": "enable a disabled account again",
    }
    for name, text in helps.items():
        change = user_sub.add_parser(name, help=text)
        change.add_argument("name")
        change.add_argument(
            "--data-dir", default=None, help="default: MISS_DATA_DIR or ./miss-data"
        )
    audit = sub.add_parser("audit", help="print the web system's audit log")
    audit.add_argument("--data-dir", default=None, help="default: MISS_DATA_DIR or ./miss-data")
    audit.add_argument("--limit", type=int, default=500, help="newest entries (default 500)")
    audit.add_argument("--action", default=None, help="only this action (login, share ...)")
    audit.add_argument("--json", action="store_true", help="one JSON object per line")


def _describe(volume: Any) -> dict[str, Any]:
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
    from miss.io import load_volume

    volume = load_volume(args.path, series=args.series)
    desc = {**_describe(volume), **label_listing(volume, args.path)}
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
    for item in desc.get("labels", []):
        print(f"label     {item['label']:<5} {item['voxels']:>10} voxels  {item['name'] or ''}")
    return 0


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


def _write_atomic(path: Path, data: bytes) -> None:
    """Write to a temporary file beside ``path`` and rename, so no half-written file is left."""
    tmp = path.with_name(f".{path.name}.part")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def cmd_convert(args: argparse.Namespace) -> int:
    from miss.errors import UnsupportedFormat
    from miss.export import WRITERS
    from miss.io import load_volume
    from miss.pipeline import JobSpec, run

    outputs = [Path(o) for o in args.output]
    formats = []
    for out in outputs:
        fmt = "".join(out.suffixes[-1:]).lower().lstrip(".")
        if fmt not in WRITERS:
            raise UnsupportedFormat(
                f"{out}: unknown output extension {out.suffix or '(none)'}; use one of "
                + ", ".join(f".{k}" for k in WRITERS)
            )
        if not out.parent.is_dir():
            raise UnsupportedFormat(f"{out}: folder {out.parent} does not exist; create it first.")
        formats.append(fmt)
    if wants_scene(args):
        return convert_scene(args, outputs, formats)
    spec = JobSpec(
        level=args.level[0],
        sample_rate=args.sample_rate,
        start_slice=args.start_slice,
        end_slice=args.end_slice,
        decimate=args.decimate,
        error_bound=args.error_bound,
        reduce=args.reduce,
        formats=tuple(dict.fromkeys(formats)),
    )
    t0 = time.perf_counter()
    volume = load_volume(args.path, series=args.series)
    t_read = time.perf_counter() - t0
    result = run(
        volume,
        spec,
        progress=_Bar(),
        title=Path(args.path).name,
        metadata={"software": "MISS", "parameters": json.dumps(spec.to_dict())},
    )
    for out, fmt in zip(outputs, formats, strict=True):
        _write_atomic(out, result.artifacts[fmt])
    seconds = {"read": t_read, **result.seconds}
    seconds["total"] = time.perf_counter() - t0
    summary = {
        "triangles": result.mesh.n_triangles,
        "vertices": result.mesh.n_vertices,
        "seconds": {k: round(v, 4) for k, v in seconds.items()},
        "outputs": [{"path": str(o), "bytes": o.stat().st_size} for o in outputs],
        "decimation": {
            "method": result.report.method,
            "reduce": result.report.reduce,
            "error_bound": result.report.error_bound,
            "achieved_reduction": round(result.report.achieved_reduction, 4),
            "triangles_before": result.report.triangles_in,
            "max_error_mm": result.report.max_error_mm,
            "mean_error_mm": result.report.mean_error_mm,
        },
    }
    if args.json:
        print(json.dumps(summary))
    else:
        d = summary["decimation"]
        print(
            f"{summary['triangles']} triangles, {summary['vertices']} vertices "
            f"({d['triangles_before']} before {d['method']} decimation; "
            f"max error {d['max_error_mm'] or 0:.3f} mm, mean {d['mean_error_mm'] or 0:.4f} mm)"
        )
        print("seconds   " + "  ".join(f"{k} {v:.2f}" for k, v in summary["seconds"].items()))
        for o in summary["outputs"]:
            print(f"wrote     {o['path']} ({o['bytes'] / 1024:.0f} KB)")
    return 0


def cmd_demo(args: argparse.Namespace) -> int:
    import nibabel as nib

    from miss.demo import phantom

    vol = phantom()
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ vol.affine  # NIfTI stores RAS
    image = nib.Nifti1Image(np.asarray(vol.data), ras)
    image.header.set_xyzt_units("mm")
    image.header["descrip"] = b"MISS CT phantom HU"
    nib.save(image, args.output)
    print(
        f"wrote {args.output}: {' x '.join(map(str, vol.dims))} voxels, HU (bone ~300, skin ~-500)"
    )
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from miss import bench
    from miss.errors import BadParameter

    try:
        rates = tuple(int(r) for r in args.sample_rates.split(","))
    except ValueError:
        raise BadParameter(
            f"--sample-rates must be integers like 1,2,4, got {args.sample_rates!r}"
        ) from None
    out = Path(args.out)
    result = bench.run_paper(
        out,
        args.repeats,
        Path(args.volume) if args.volume else None,
        rates,
        log=lambda line: print(line, file=sys.stderr),
    )
    print(bench.markdown(bench.rows_from_json(result)))
    print(f"wrote {out / 'paper_tables.json'}, .md and .png")
    return 0


def cmd_serve(args: argparse.Namespace) -> int:
    from miss.server.main import serve

    return serve(host=args.host, port=args.port, data_dir=args.data_dir)


def _read_password() -> str:
    """The new password: typed twice at a terminal, else the first line of stdin."""
    if sys.stdin.isatty():
        import getpass

        first = getpass.getpass("password: ")
        if getpass.getpass("again: ") != first:
            from miss.errors import BadParameter

            raise BadParameter("the two passwords differ; run the command again.")
        return first
    return sys.stdin.readline().rstrip("\r\n")


def cmd_user(args: argparse.Namespace) -> int:
    """``miss user add|passwd|disable|enable NAME``. A running server drops the ended
    logins within seconds (it checks its live sessions against the database)."""
    from miss.server import accounts, audit
    from miss.server.settings import Settings
    from miss.server.store import Store

    settings = Settings.from_env(data_dir=args.data_dir)
    store = Store(settings.data_dir, settings.database_url)
    try:
        store.init_schema()
        if args.user_command == "add":
            user = accounts.create_user(store, args.name, _read_password(), is_admin=args.admin)
            said = f"created {'administrator' if user.is_admin else 'user'} {user.name!r}"
        else:
            user = accounts.find_user(store, args.name)
            if args.user_command == "passwd":
                accounts.set_password(store, user.id, _read_password())
            else:
                accounts.set_disabled(store, user.id, args.user_command == "disable")
            ended = [] if args.user_command == "enable" else accounts.end_sessions(store, user.id)
            audit.record(store, f"user_{args.user_command}", "(command line)", user.name)
            said = f"{args.user_command}: {user.name!r} ({len(ended)} login(s) ended)"
    finally:
        store.close()
    print(said)
    return 0


def cmd_audit(args: argparse.Namespace) -> int:
    from miss.server import audit
    from miss.server.settings import Settings
    from miss.server.store import Store

    settings = Settings.from_env(data_dir=args.data_dir)
    store = Store(settings.data_dir, settings.database_url)
    try:
        store.init_schema()
        entries = audit.entries(store, args.limit, args.action)
    finally:
        store.close()
    for entry in entries:
        print(json.dumps(entry) if args.json else audit.format_line(entry))
    return 0


COMMANDS = {
    "info": cmd_info,
    "convert": cmd_convert,
    "demo": cmd_demo,
    "bench": cmd_bench,
    "serve": cmd_serve,
    "user": cmd_user,
    "audit": cmd_audit,
}


def main(argv: Sequence[str] | None = None) -> int:
    from miss.errors import MissError

    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except MissError as exc:
        print(f"miss: {exc}", file=sys.stderr)
    except MemoryError:
        print(
            "miss: out of memory; use a larger --sample-rate or a smaller slice range",
            file=sys.stderr,
        )
    except OSError as exc:
        print(
            f"miss: {exc.filename or ''}: {exc.strerror or exc}; check the path and permissions",
            file=sys.stderr,
        )
    except KeyboardInterrupt:
        print("miss: interrupted", file=sys.stderr)
    return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
