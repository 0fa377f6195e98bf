"""``miss pacs search|series|get|send``: the hospital's PACS from the command line.

The PACS is the one ``MISS_PACS_URL`` names (``--pacs NAME`` picks another of
``MISS_PACS2_URL`` ...); credentials come from the file ``MISS_PACS_AUTH_FILE`` names,
never from the command line. ``miss convert dicomweb:STUDY/SERIES`` models a series
straight from the PACS. ``miss pacs send`` stores a model only in a study that the PACS
says is there, has the ``--patient-id`` given and holds the ``--series`` named: a study UID
copied from the wrong line of a search cannot file a model under another patient.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any


def add_arguments(pacs: argparse.ArgumentParser) -> None:
    """``miss pacs search|series|...``: one subcommand per PACS question."""
    pacs_sub = pacs.add_subparsers(dest="pacs_command", required=True, parser_class=type(pacs))
    search = pacs_sub.add_parser("search", help="find studies (QIDO-RS)")
    for flag, text in (
        ("--patient-id", "patient ID"),
        ("--patient-name", "patient name (a prefix, or with * wildcards)"),
        ("--accession", "accession number"),
        ("--study-date", "YYYYMMDD or a range YYYYMMDD-YYYYMMDD"),
        ("--modality", "a modality in the study (CT, MR ...)"),
    ):
        search.add_argument(flag, default=None, help=text)
    search.add_argument("--limit", type=int, default=25, help="studies at most (25)")
    series = pacs_sub.add_parser("series", help="list a study's series")
    series.add_argument("study", help="Study Instance UID")
    get = pacs_sub.add_parser("get", help="fetch a series' DICOM files into a folder (WADO-RS)")
    get.add_argument("study", help="Study Instance UID")
    get.add_argument("series", help="Series Instance UID")
    get.add_argument("-o", "--output", required=True, help="folder (made if missing)")
    send = pacs_sub.add_parser(
        "send", help="store a model (.stl, or a scene's .zip of STLs) in a study (STOW-RS)"
    )
    send.add_argument("model", help="the model: an .stl, or the .zip miss convert writes")
    send.add_argument("--study", required=True, help="Study Instance UID to store it in")
    send.add_argument(
        "--patient-id", required=True,
        help="the patient ID the study must have on the PACS (checked before storing)",
    )  # fmt: skip
    send.add_argument(
        "--series", default=None,
        help="the image series it was made from: its frame of reference and images are named",
    )  # fmt: skip
    send.add_argument("--description", default=None, help="the new series' description")
    for command in (search, series, get, send):
        command.add_argument("--pacs", default=None, help="which PACS (default: the first)")
        command.add_argument("--json", action="store_true", help="print JSON")


def cmd_pacs(args: argparse.Namespace) -> int:
    """Ask the PACS what the subcommand asks and print the answer; the exit status."""
    from miss.pacs.source import pick_server

    server = pick_server(args.pacs)
    answer = COMMANDS[args.pacs_command](server, args)
    if args.json:
        print(json.dumps(answer))
    return 0


def _search(server: Any, args: argparse.Namespace) -> Any:
    from miss.pacs import client

    given = {name: getattr(args, name) for name in client.FILTERS}
    page = client.search_studies(server, client.search_filters(given), 0, args.limit)
    if not args.json:
        for s in page.rows:
            print(
                f"{s['study']}  {s['study_date'] or '-':8}  {s['patient_id']:<16} "
                f"{s['patient_name'][:24]:<24} {','.join(s['modalities']):<8} "
                f"{s['series_count'] or 0:>3} series  {s['description']}"
            )
        print(f"{len(page.rows)} stud{'y' if len(page.rows) == 1 else 'ies'}"
              + (" (more: raise --limit or narrow the search)" if page.more else ""))  # fmt: skip
    return {"studies": page.rows, "more": page.more}


def _series(server: Any, args: argparse.Namespace) -> Any:
    from miss.pacs import client

    rows = client.search_series(server, args.study)
    if not args.json:
        for s in rows:
            said = "" if s["importable"] else f"  ({s['reason']})"
            print(
                f"{s['series']}  {s['modality']:<8} {s['instances'] or 0:>5} instances  "
                f"{s['description']}{said}"
            )
    return rows


def _get(server: Any, args: argparse.Namespace) -> Any:
    from miss.pacs import client
    from miss.pacs.source import MAX_BYTES

    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    if any(out.iterdir()):
        from miss.errors import BadParameter

        raise BadParameter(f"{out} is not empty; give a new or empty folder.")
    instances = client.list_instances(server, args.study, args.series, 5000)
    written = client.retrieve_series(
        server, args.study, args.series, out, MAX_BYTES, len(instances), images=False
    )
    if not args.json:
        print(f"wrote     {len(written)} DICOM file(s) to {out}")
    return {"files": [str(p) for p in written]}


def _send(server: Any, args: argparse.Namespace) -> Any:
    from miss import __version__
    from miss.pacs import client
    from miss.pacs.stl import encapsulate

    parts = model_parts(Path(args.model))
    origin = client.study_origin(server, args.study, args.series, args.patient_id)
    description = args.description or f"MISS surface: {Path(args.model).stem}"
    datasets = encapsulate(parts, origin, description, f"MISS {__version__}")
    stored = client.store(server, datasets, args.study)
    if not args.json:
        print(f"stored    {len(stored)} Encapsulated STL instance(s) in study {args.study}")
        for uid in stored:
            print(f"instance  {uid}")
    return {"series_uid": str(datasets[0].SeriesInstanceUID), "sop_instance_uids": stored}


def model_parts(path: Path) -> list[tuple[str, bytes]]:
    """(title, STL bytes) of an ``.stl`` or of a scene's ``.zip`` (one STL a part and
    ``scene.json``, as ``miss convert`` writes it)."""
    import io
    import zipfile

    from miss.errors import UnreadableVolume, UnsupportedFormat

    try:
        data = path.read_bytes()
    except OSError as exc:
        raise UnreadableVolume(f"{path}: {exc.strerror}; check the path.") from None
    if data.startswith(b"PK\x03\x04"):
        try:
            with zipfile.ZipFile(io.BytesIO(data)) as archive:
                scene = json.loads(archive.read("scene.json"))
                return [(p["name"], archive.read(p["file"])) for p in scene["parts"]]
        except (KeyError, ValueError, zipfile.BadZipFile):
            raise UnreadableVolume(
                f"{path}: not a MISS scene zip (no scene.json); give the .stl or the .zip "
                "that miss convert wrote."
            ) from None
    if path.suffix.lower() != ".stl" or len(data) < 84:
        raise UnsupportedFormat(f"{path}: send an .stl, or the scene .zip miss convert writes.")
    return [(path.stem, data)]


COMMANDS = {"search": _search, "series": _series, "get": _get, "send": _send}
