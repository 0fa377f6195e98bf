"""``miss ingest``: store a (big) volume in the server's data folder once, for many jobs.

The volume is stored as an upload is (same de-identification, files and row); a plain
NIfTI-1 file (``.nii``, ``.nii.gz``) is read plane by plane, so a 5 GB scan never needs
5 GB of memory. Safe beside a running server of the same data folder.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(ingest: argparse.ArgumentParser) -> None:
    """``miss ingest``: the scan to add, the name to list it by and the data folder."""
    ingest.add_argument("path", help="DICOM folder/zip, NIfTI, NRRD or MetaImage file")
    ingest.add_argument(
        "--name",
        default="",
        help="name to list (default: modality, body part and series description)",
    )
    ingest.add_argument("--data-dir", default=None, help="default: MISS_DATA_DIR or ./miss-data")


def cmd_ingest(args: argparse.Namespace) -> int:
    """Print the new volume's id."""
    from miss.errors import BadParameter
    from miss.server import audit
    from miss.server.core.settings import Settings
    from miss.server.storage.private import owner_only
    from miss.server.storage.store import Store
    from miss.server.volumes.ingest import ingest_path

    path = Path(args.path)
    if not path.exists():
        raise BadParameter(f"{path}: no such file or folder; check the path.")
    settings = Settings.from_env(data_dir=args.data_dir)
    owner_only(settings.data_dir, settings.database_url)
    store = Store(settings.data_dir, settings.database_url, settings.in_memory_max_bytes)
    try:
        store.init_schema()
        (settings.data_dir / "volumes").mkdir(exist_ok=True)
        (settings.data_dir / "tmp").mkdir(exist_ok=True)
        row = ingest_path(store, path, args.name)
        audit.record(store, "upload", "(command line)", row.id, name=row.name)
    finally:
        store.close()
    print(row.id)
    return 0
