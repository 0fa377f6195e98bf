"""Decompression caps every reader applies before it decodes (issue 39).

A few hundred bytes of bzip2 can declare, and decode to, gigabytes of zeros: a 499-byte
NRRD was stored as a 512 MiB volume, and a 1.6 KB one declaring 2048 x 2048 x 512 ran
38 s at 4.1 GB. So every compressed input is held to a ratio and a total,
on the size its header declares, before a byte is decoded:

- past ``RATIO_FLOOR`` (64 MiB) decoded, at most ``MAX_RATIO`` (1032, what deflate can
  reach) times the compressed bytes (CT and MR compress 2-10:1, mostly empty volumes and
  label maps 100:1 and more);
- in all, at most :func:`max_decoded` bytes (``MISS_MAX_UNZIPPED_MB`` on a server, as
  for a zip; its default, 8 GiB, elsewhere).

Then :func:`inflate` decodes streaming and stops at the declared size, so data that
inflates further (trailing bombs) never does. Which codecs each reader accepts: NRRD
gzip (or zlib) and bzip2; MetaImage zlib; NIfTI gzip; DICOM deflate (the whole data
set, :func:`check_deflated_dicom`) and its pixel codecs (JPEG, JPEG 2000, RLE: the
declared frames against the file's bytes); SimpleITK's catch-all formats (TIFF, PNG,
MINC, MGZ, ... whatever their codec: the declared image against the bytes beside it).
No reader accepts lzma/xz or zstd data; :func:`inflate` knows xz for completeness.
"""

from __future__ import annotations

import bz2
import lzma
import math
import zlib
from collections.abc import Sequence
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from miss.errors import InputTooLarge, UnsafeArchive

#: Decoded bytes per compressed byte beyond which data is refused once past
#: ``RATIO_FLOOR`` decoded bytes: deflate's own ceiling (about 1032:1), so no real gzip is
#: refused (an 800 MiB CT with much air compresses 117:1, a label map with empty slices
#: more), and bzip2, which can go a thousand times further, is held to it.
MAX_RATIO = 1032
#: The same for the members of a zip upload (:mod:`miss.io.archive`), DICOM slices that
#: deflate 2-10:1: the zip rule.
ZIP_RATIO = 100
RATIO_FLOOR = 64 * 1024**2
#: ``MISS_MAX_UNZIPPED_MB``'s default (4 x the 2048 MB upload limit), in bytes.
DEFAULT_MAX_DECODED = 8 * 1024**3
#: Compressed bytes fed to a decoder at a time.
CHUNK = 1 << 20
#: DICOM's Deflated Explicit VR Little Endian transfer syntax.
DEFLATED_DICOM = "1.2.840.10008.1.2.1.99"

_max_decoded = [DEFAULT_MAX_DECODED]


def set_max_decoded(limit: int) -> None:
    """Cap, in bytes, what any one input may decode to (the confined child sets the
    server's ``MISS_MAX_UNZIPPED_MB``); 0 or less restores the default."""
    _max_decoded[0] = int(limit) if limit > 0 else DEFAULT_MAX_DECODED


def max_decoded() -> int:
    """Bytes any one input may decode to (:func:`set_max_decoded`)."""
    return _max_decoded[0]


def size_text(n: float) -> str:
    """``n`` bytes for people: ``4 GiB``, ``1.6 KB``, ``499 bytes``."""
    for unit, scale in (("GiB", 1024**3), ("MiB", 1024**2), ("KB", 1024)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{int(n)} bytes"


def declared_text(shape: Sequence[int], dtype: np.dtype | str) -> str:
    """``2048x2048x512 int16`` for messages."""
    return f"{'x'.join(str(int(n)) for n in shape)} {np.dtype(dtype).name}"


def check_decoded(path: Path, decoded: int, compressed: int, codec: str, what: str = "") -> None:
    """Refuse, before decoding, ``decoded`` bytes from ``compressed`` bytes of ``codec``
    data over the total cap (``InputTooLarge``, 413) or the ratio rule (``UnsafeArchive``,
    422). ``what`` describes the declared image (``2048x2048x512 int16``) for the message.
    """
    declared = f"{what} ({size_text(decoded)})" if what else size_text(decoded)
    limit = max_decoded()
    if decoded > limit:
        raise InputTooLarge(
            f"{path.name}: declares {declared} of voxels, more than the {size_text(limit)} "
            "one file may decode to; send a smaller volume or raise MISS_MAX_UNZIPPED_MB on "
            "the server."
        )
    if decoded > RATIO_FLOOR and decoded > MAX_RATIO * max(compressed, 1):
        raise UnsafeArchive(
            f"{path.name}: declares {declared} from {size_text(compressed)} of {codec}: more "
            f"than {MAX_RATIO} times its size, far beyond what scans compress to (a "
            "decompression bomb?); save the scan uncompressed or with its usual "
            "compression, or fix the sizes in its header."
        )


def check_declared(
    path: Path, shape: Sequence[int], dtype: np.dtype | str, compressed: int, codec: str
) -> None:
    """:func:`check_decoded` for an image of ``shape`` (any axes) and ``dtype``."""
    decoded = math.prod(int(n) for n in shape) * np.dtype(dtype).itemsize
    check_decoded(path, decoded, compressed, codec, declared_text(shape, dtype))


def bytes_on_disk(path: Path) -> int:
    """Bytes of the file ``path``, or of every file under the folder ``path``."""
    if path.is_dir():
        return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())
    return path.stat().st_size if path.is_file() else 0


def _decoder(codec: str) -> Any:
    if codec in ("gzip", "zlib"):  # wbits 47: a gzip or a zlib header, detected
        return zlib.decompressobj(zlib.MAX_WBITS | 32)
    if codec == "deflate":
        return zlib.decompressobj(-zlib.MAX_WBITS)
    if codec == "bzip2":
        return bz2.BZ2Decompressor()
    if codec in ("xz", "lzma"):
        return lzma.LZMADecompressor()
    raise ValueError(f"unknown codec {codec!r}")


def inflate(data: bytes | memoryview, codec: str, limit: int, concatenated: bool = True) -> bytes:
    """At most ``limit`` decoded bytes of ``codec`` data (``gzip``/``zlib``, raw
    ``deflate``, ``bzip2``, ``xz``); the decoder never makes more than ``limit`` (it is
    asked for what is left each time).

    ``concatenated``: stream after stream (NRRD), and ``EOFError`` when the data ends
    before ``limit`` bytes; else the first stream only, however short (MetaImage: what
    follows it is ignored). Damaged data raises ``zlib.error``, ``OSError`` or
    ``ValueError`` (``LZMAError`` included).
    """
    out = bytearray()
    data = memoryview(data)
    while len(data) and len(out) < limit:
        decoder = _decoder(codec)
        out += decoder.decompress(data, limit - len(out))
        if not concatenated:
            break
        if len(out) < limit and not decoder.eof:
            raise EOFError("the compressed stream ends before the data does")
        data = memoryview(decoder.unused_data)
    return bytes(out)


def deflated_size(stream: BinaryIO, limit: int) -> int:
    """Bytes the rest of ``stream`` (raw deflate) inflates to, counted chunk by chunk and
    never held, stopping once past ``limit`` (then more than ``limit``). Damaged data:
    what it gave so far (the reader that decodes it for real reports the damage)."""
    decoder, total = zlib.decompressobj(-zlib.MAX_WBITS), 0
    try:
        while total <= limit and not decoder.eof and (chunk := stream.read(CHUNK)):
            while chunk and total <= limit:
                total += len(decoder.decompress(chunk, CHUNK))
                chunk = decoder.unconsumed_tail
    except zlib.error:
        pass
    return total


def check_deflated_dicom(path: Path, stream: BinaryIO) -> None:
    """Refuse a DICOM file in the deflated transfer syntax whose data set inflates past
    the caps, before pydicom inflates it whole (it does, for a header alone). ``stream``
    is at the file's start and is left there; other transfer syntaxes pass untouched."""
    from pydicom.filereader import _read_file_meta_info, read_preamble

    try:
        read_preamble(stream, False)
        syntax = str(_read_file_meta_info(stream).get("TransferSyntaxUID", ""))
    except Exception:  # noqa: BLE001 - not DICOM, or damaged: pydicom says so itself
        syntax = ""
    if syntax == DEFLATED_DICOM:
        start = stream.tell()
        compressed = stream.seek(0, 2) - start
        stream.seek(start)
        cap = min(max_decoded(), max(RATIO_FLOOR, ZIP_RATIO * compressed))
        if deflated_size(stream, cap) > cap:
            stream.seek(0)
            raise _bomb_or_too_large(path, cap, compressed)
    stream.seek(0)


def _bomb_or_too_large(path: Path, cap: int, compressed: int) -> InputTooLarge | UnsafeArchive:
    if cap >= max_decoded():
        return InputTooLarge(
            f"{path.name}: its deflated DICOM data set inflates to more than the "
            f"{size_text(cap)} one file may decode to; send a smaller file or raise "
            "MISS_MAX_UNZIPPED_MB on the server."
        )
    return UnsafeArchive(
        f"{path.name}: its deflated DICOM data set inflates to more than {size_text(cap)} "
        f"from {size_text(compressed)}: more than {ZIP_RATIO} times its size, far beyond "
        "what scans compress to (a decompression bomb?); export it again without the "
        "deflated transfer syntax."
    )
