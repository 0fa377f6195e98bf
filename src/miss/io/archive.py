"""Unpacking an uploaded zip safely, and picking what to read from it.

Members are unpacked one by one with the inflated bytes counted (declared sizes can
lie), after checking that none would land outside the folder (``../``, absolute paths,
symbolic links) and that the archive as a whole is neither over the byte budget nor
compressed far beyond what scans compress to. The per-member ratio check alone let a
few MB of zip holding many 60 MB members of zeros write gigabytes, so the budget and
the ratio are checked for the whole archive too, on the declared sizes first and on
the real bytes while writing.
"""

from __future__ import annotations

import re
import stat
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path, PurePosixPath

from miss.errors import BadParameter, InputTooLarge, UnreadableVolume, UnsafeArchive
from miss.io.codecs import RATIO_FLOOR, ZIP_RATIO

CHUNK = 1 << 20
MAX_MEMBERS = 100_000
#: Inflated bytes per zipped byte beyond which an archive (or one member) is refused once
#: past ``RATIO_FLOOR``: CT and MR slices deflate about 2-10:1, masks a little more. The
#: same rule holds for every compressed file a reader decodes (:mod:`miss.io.codecs`).
#: Extensions of single-file volumes, longest first so ".nii.gz" wins over ".gz".
VOLUME_SUFFIXES = (".nii.gz", ".nii", ".nrrd", ".nhdr", ".mha", ".mhd")

#: Called with the bytes written so far, every ``CHUNK``: raises to stop (a full disk).
Progress = Callable[[int], None]


def is_zip(path: Path) -> bool:
    """True for a ``.zip`` name or zip magic in the first four bytes."""
    with open(path, "rb") as f:
        head = f.read(4)
    return path.suffix.lower() == ".zip" or head in (b"PK\x03\x04", b"PK\x05\x06")


def too_large(what: str, limit: int) -> str:
    """The message for a ``what`` over ``limit`` bytes, naming the settings that raise it."""
    return (
        f"the {what} is larger than the limit of {limit / 2**20:g} MB; send a smaller "
        "series or raise MISS_MAX_UPLOAD_MB / MISS_MAX_UNZIPPED_MB on the server."
    )


def _member_path(info: zipfile.ZipInfo) -> PurePosixPath | None:
    """The member's relative path, None for junk to skip; raises for unsafe members."""
    name = info.filename.replace("\\", "/")
    if not name:
        raise UnreadableVolume(
            "the zip holds a member without a name: its directory is damaged; create the zip again."
        )
    if name.startswith("/") or re.match(r"^[A-Za-z]:", name):
        raise UnsafeArchive(
            f"zip member {info.filename!r} has an absolute path; zip relative paths only."
        )
    parts = PurePosixPath(name).parts
    if ".." in parts:
        raise UnsafeArchive(
            f"zip member {info.filename!r} points outside the archive ('..'); "
            "zip the folder itself."
        )
    if info.create_system == 3 and stat.S_ISLNK(info.external_attr >> 16):
        raise UnsafeArchive(
            f"zip member {info.filename!r} is a symbolic link; zip real files only."
        )
    if info.is_dir() or not parts or parts[0] == "__MACOSX" or parts[-1].startswith("._"):
        return None
    return PurePosixPath(*parts)


def extract_zip(path: Path, dest: Path, max_bytes: int, progress: Progress | None = None) -> None:
    """Unpack ``path`` into ``dest``: unsafe members, more than ``max_bytes`` in all, or more
    than ``ZIP_RATIO`` times the archive's size (past ``RATIO_FLOOR``) are refused."""
    archive = max(path.stat().st_size, 1)
    budget = min(max_bytes, max(RATIO_FLOOR, ZIP_RATIO * archive))
    try:
        with zipfile.ZipFile(path) as zf:
            infos = zf.infolist()
            if len(infos) > MAX_MEMBERS:
                raise UnsafeArchive(
                    f"the zip has {len(infos)} members; at most {MAX_MEMBERS} are accepted."
                )
            members = [(info, rel) for info in infos if (rel := _member_path(info)) is not None]
            declared = sum(info.file_size for info, _ in members)
            if declared > max_bytes:
                raise InputTooLarge(too_large("unzipped content", max_bytes))
            _refuse_bombs(archive, [info for info, _ in members], declared)
            total = 0
            for info, rel in members:
                limits = (budget, max_bytes, archive)
                total = _extract_member(zf, info, dest / rel, total, limits, progress)
    except (zipfile.BadZipFile, zlib.error, EOFError, UnicodeDecodeError) as exc:
        # UnicodeDecodeError: names flagged UTF-8 that are not (a damaged directory).
        raise UnreadableVolume(
            f"{path.name}: not a valid zip archive ({exc}); create the zip again."
        ) from None
    except (NotImplementedError, RuntimeError) as exc:  # unsupported compression, encryption
        raise UnreadableVolume(
            f"{path.name}: cannot unpack ({exc}); use a plain, unencrypted zip."
        ) from None


def _bomb(what: str, packed: int, size: int) -> UnsafeArchive:
    return UnsafeArchive(
        f"{what} would inflate {packed} bytes to {size / 2**20:.0f} MB "
        f"({size / max(packed, 1):.0f}:1), far beyond what scans compress to (a zip "
        "bomb?); zip the slice files themselves again."
    )


def _refuse_bombs(archive: int, infos: list[zipfile.ZipInfo], declared: int) -> None:
    """Members, and the archive (``archive`` bytes) as a whole, that would inflate far
    beyond what scans compress to, refused from the declared sizes before anything is
    written."""
    if declared > RATIO_FLOOR and declared > ZIP_RATIO * archive:
        raise _bomb("the zip", archive, declared)
    for info in infos:
        size, packed = info.file_size, max(info.compress_size, 1)
        if size > RATIO_FLOOR and size > ZIP_RATIO * packed:
            raise _bomb(f"zip member {info.filename!r}", packed, size)


def _extract_member(
    zf: zipfile.ZipFile,
    info: zipfile.ZipInfo,
    target: Path,
    total: int,
    limits: tuple[int, int, int],
    progress: Progress | None,
) -> int:
    """Copy one member, counting real inflated bytes against (ratio budget, byte limit,
    archive size)."""
    budget, limit, archive = limits
    target.parent.mkdir(parents=True, exist_ok=True)
    with zf.open(info) as src, open(target, "wb") as out:
        while chunk := src.read(CHUNK):
            total += len(chunk)
            if total > limit:
                raise InputTooLarge(too_large("unzipped content", limit))
            if total > budget:
                raise _bomb("the zip", archive, total)
            out.write(chunk)
            if progress is not None:
                progress(total)
    return total


def volume_suffix(path: Path) -> str:
    """The volume extension ``path`` ends with (``.nii.gz`` ...), else ``""``."""
    name = path.name.lower()
    return next((s for s in VOLUME_SUFFIXES if name.endswith(s)), "")


def pick_source(folder: Path) -> Path:
    """What to read from an unpacked zip (or the files of one upload, gathered): its single
    volume file, else the folder (DICOM)."""
    files = [p for p in folder.rglob("*") if p.is_file()]
    if not files:
        raise UnreadableVolume(
            "the zip is empty; zip the folder of DICOM slices (or one volume file)."
        )
    singles = sorted(p for p in files if volume_suffix(p))
    if len(singles) > 1:
        names = ", ".join(str(p.relative_to(folder)) for p in singles[:5])
        raise BadParameter(f"the upload holds several volumes ({names}); upload one at a time.")
    return singles[0] if singles else folder
