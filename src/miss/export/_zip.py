"""Deterministic zips, for the formats that are packages (3MF).

The zip is byte-for-byte reproducible: fixed timestamps (1980-01-01, the format's
epoch), fixed permissions, deflate at zlib's default level, entries in the order given.
"""

from __future__ import annotations

import io
import zipfile

_EPOCH = (1980, 1, 1, 0, 0, 0)


def zip_files(files: list[tuple[str, bytes]]) -> bytes:
    """A deterministic zip of ``(name, data)`` entries, in order."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        for name, data in files:
            info = zipfile.ZipInfo(name, date_time=_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16  # -rw-r--r-- when unpacked on Unix
            archive.writestr(info, data)
    return buffer.getvalue()
