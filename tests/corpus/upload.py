"""A corpus case as the upload API takes it (used by the API tests and the robustness benchmark)."""

from __future__ import annotations

import zipfile
from pathlib import Path


def _member_name(name: str) -> str:
    """A file name as a zip can hold it (undecodable bytes of the corpus made readable)."""
    return name.encode("utf-8", "surrogateescape").decode("utf-8", "replace")


def as_upload(path: Path, root: Path, dest: Path) -> Path:
    """A folder (a DICOM series, or a header with its data file beside it) zipped into
    ``dest`` with the folder inside; a file directly under ``root`` as it is."""
    folder = path if path.is_dir() else path.parent if path.parent != root else None
    if folder is None:
        return path
    out = dest / f"{folder.name}.zip"
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
        for f in sorted(folder.rglob("*")):
            if f.is_file():
                zf.write(f, _member_name(f"{folder.name}/{f.relative_to(folder)}"))
    return out
