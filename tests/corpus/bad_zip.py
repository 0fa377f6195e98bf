"""Zip archives of a DICOM series that are hostile or broken: bombs, escaping names, links."""

from __future__ import annotations

import stat
from typing import TYPE_CHECKING

from corpus.files import (
    dicom_bytes,
    dicom_slice,
    raw_member,
    raw_zip,
    zeros_member,
    zip_bytes,
)

if TYPE_CHECKING:
    from corpus.cases import Writer

#: The ratio bomb inflates to this much (1 GiB of zeros in about 1 MB).
BOMB_BYTES = 1 << 30


def slices(prefix: str = "series/", count: int = 4) -> dict[str, bytes]:
    return {f"{prefix}IM{k + 1:04d}.dcm": dicom_bytes(dicom_slice(k)) for k in range(count)}


def write(w: Writer) -> None:
    _plain(w)
    _names(w)
    _bombs(w)


def _plain(w: Writer) -> None:
    good = zip_bytes(slices())
    w.file("zip-dicom-valid", ".zip", good, "zip", "ok", "the reference: 4 slices in a folder")
    w.file(
        "zip-stored-no-folder",
        ".zip",
        zip_bytes(slices(""), method=0),
        "zip",
        "ok",
        "uncompressed members at the archive root",
    )
    w.file("zip-empty", ".zip", zip_bytes({}), "zip", "error", "an archive with no members")
    w.file(
        "zip-only-folders",
        ".zip",
        zip_bytes({"a/": b"", "a/b/": b""}),
        "zip",
        "error",
        "directory entries only",
    )
    w.file(
        "zip-truncated",
        ".zip",
        good[: len(good) // 2],
        "zip",
        "error",
        "cut in half: no central directory",
    )
    w.file(
        "zip-nested-zip",
        ".zip",
        zip_bytes({"inner.zip": good}),
        "zip",
        "error",
        "a zip inside a zip: not unpacked recursively",
    )
    encrypted = [raw_member(n.encode(), d, flags=0x1) for n, d in slices().items()]
    w.file(
        "zip-encrypted",
        ".zip",
        raw_zip(encrypted),
        "zip",
        "error",
        "members flagged as encrypted (no password can be given)",
    )
    lzma_like = [raw_member(n.encode(), d, method=99) for n, d in slices().items()]
    w.file(
        "zip-unknown-method",
        ".zip",
        raw_zip(lzma_like),
        "zip",
        "error",
        "compression method 99 (AES), which zipfile cannot inflate",
    )
    nameless = [*[raw_member(n.encode(), d) for n, d in slices().items()], raw_member(b"", b"x")]
    w.file(
        "zip-member-without-name",
        ".zip",
        raw_zip(nameless),
        "zip",
        "error",
        "a member whose name is empty beside good slices: the directory is damaged",
    )
    lying = [raw_member(b"IM0001.dcm", bytes(16 << 20), size=100)]
    w.file(
        "zip-size-lies",
        ".zip",
        raw_zip(lying),
        "zip",
        "error",
        "a member declares 100 bytes but inflates to 16 MB: read stops at 100, CRC fails",
    )


def _names(w: Writer) -> None:
    for name, member, why in (
        ("zip-parent-member", "../IM0001.dcm", "a '..' member climbs out of the archive"),
        (
            "zip-parent-member-backslash",
            "series\\..\\..\\IM0001.dcm",
            "'..' spelled with backslashes",
        ),
        ("zip-absolute-member", "/tmp/IM0001.dcm", "an absolute member name"),
        ("zip-drive-letter-member", "C:/IM0001.dcm", "a Windows drive-letter member name"),
    ):
        w.file(
            name,
            ".zip",
            zip_bytes(slices() | {member: dicom_bytes(dicom_slice(9))}),
            "zip",
            "error",
            why,
        )
    link = raw_member(b"series/IM0009.dcm", b"/etc/passwd", unix_mode=stat.S_IFLNK | 0o777)
    members = [raw_member(n.encode(), d) for n, d in slices().items()]
    w.file(
        "zip-symlink-member",
        ".zip",
        raw_zip([*members, link]),
        "zip",
        "error",
        "a symbolic-link member among good slices: the archive is not trusted",
    )
    cp437 = [raw_member(b"S\x82RIE/IM\x81%d.dcm" % k, d) for k, d in enumerate(slices().values())]
    w.file(
        "zip-cp437-names",
        ".zip",
        raw_zip(cp437),
        "zip",
        "ok",
        "names in bytes that are not UTF-8 and no UTF-8 flag: decoded as cp437, read",
    )
    bad_utf8 = [
        raw_member(b"caf\xe9/IM%d.dcm" % k, d, flags=0x800) for k, d in enumerate(slices().values())
    ]
    w.file(
        "zip-invalid-utf8-names",
        ".zip",
        raw_zip(bad_utf8),
        "zip",
        "error",
        "the UTF-8 flag is set but the names are latin-1 bytes: the directory is damaged",
    )


def _bombs(w: Writer) -> None:
    members = [raw_member(n.encode(), d) for n, d in slices().items()]
    bomb = zeros_member(b"series/IM0005.dcm", BOMB_BYTES)
    w.file(
        "zip-bomb-ratio",
        ".zip",
        raw_zip([*members, bomb]),
        "zip",
        "error",
        "1 GiB of zeros deflated 1000:1 beside 4 slices: refused from the sizes, not inflated",
    )
    huge = [raw_member(b"IM%04d.dcm" % k, bytes(64), size=0xFFFF0000) for k in range(3)]
    w.file(
        "zip-bomb-declared-huge",
        ".zip",
        raw_zip(huge),
        "zip",
        "error",
        "the directory declares 3 x 4 GB: refused before reading any member",
    )
