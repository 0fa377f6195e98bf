"""Decompression bombs in every codec a reader accepts (issue 39): a 499-byte bzip2 NRRD
was stored as a 512 MiB volume, a 1.6 KB one declaring 2048 x 2048 x 512 ran 38 s at
4.1 GB. Each bomb here is a few kB to a few hundred kB declaring (and, on the old code,
decoding to) 256 MiB of zeros: refused from its header before decoding, by the real CLI
(one line, exit 2, its peak memory far below what it declares) and by a real server
(422 with the message, nothing kept)."""

from __future__ import annotations

import bz2
import gzip
import io
import struct
import subprocess
import sys
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from support.realserver import Server, serving

from miss.io import codecs

MiB = 1 << 20
#: What every bomb declares: 512 x 512 x 512 int16, 256 MiB (past the 64 MiB floor).
SIDE, DECLARED = 512, 256 * MiB
#: What its stream holds: 8 MiB of zeros, a few KB compressed. The header lies, as an
#: attacker's does; an honest deflate stream cannot pass 1032:1 (``codecs.MAX_RATIO``),
#: so it is bounded by the total cap, not refused as a bomb.
ZEROS = bytes(8 * MiB)
HELD = len(ZEROS)


def _repeated(compress: Callable[[bytes], bytes]) -> bytes:
    """``HELD`` zeros as one stream (NRRD would read concatenated ones too)."""
    return compress(ZEROS) * (HELD // len(ZEROS))


def _one_stream(compressor: object, total: int = HELD) -> bytes:
    parts = [compressor.compress(ZEROS) for _ in range(total // len(ZEROS))]  # type: ignore[attr-defined]
    return b"".join(parts) + compressor.flush()  # type: ignore[attr-defined]


def nrrd(
    encoding: str, data: bytes, sizes: str = f"{SIDE} {SIDE} {SIDE}", extra: str = ""
) -> bytes:
    head = f"NRRD0004\ntype: int16\ndimension: 3\nsizes: {sizes}\nencoding: {encoding}\n{extra}\n"
    return head.encode() + data


def nrrd_bzip2() -> tuple[str, bytes]:
    return "bomb.nrrd", nrrd("bzip2", _repeated(bz2.compress))


def nrrd_gzip() -> tuple[str, bytes]:
    return "bomb.nrrd", nrrd("gzip", _repeated(lambda b: gzip.compress(b, 9, mtime=0)))


def nrrd_byte_skip() -> tuple[str, bytes]:
    """A small volume behind a 256 MiB ``byte skip``: the skipped bytes are inflated too."""
    data = _repeated(bz2.compress) + bz2.compress(bytes(2 * 16**3))
    return "skip.nrrd", nrrd("bzip2", data, "16 16 16", f"byte skip: {DECLARED}\n")


def metaimage_zlib() -> tuple[str, bytes]:
    head = (
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n"
        f"CompressedData = True\nDimSize = {SIDE} {SIDE} {SIDE}\nElementType = MET_SHORT\n"
        "ElementDataFile = LOCAL\n"
    )
    return "bomb.mha", head.encode() + _one_stream(zlib.compressobj(9))


def nifti_gzip() -> tuple[str, bytes]:
    header = bytearray(352)
    struct.pack_into("<i", header, 0, 348)
    struct.pack_into("<8h", header, 40, 3, SIDE, SIDE, SIDE, 1, 1, 1, 1)
    struct.pack_into("<hh", header, 70, 4, 16)  # int16
    struct.pack_into("<8f", header, 76, 1, 1, 1, 1, 1, 1, 1, 1)
    struct.pack_into("<f", header, 108, 352.0)
    struct.pack_into("<h", header, 254, 1)  # sform_code
    struct.pack_into("<12f", header, 280, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0)
    header[344:348] = b"n+1\0"
    compressor = zlib.compressobj(9, zlib.DEFLATED, 31)  # a gzip stream
    return "bomb.nii.gz", compressor.compress(bytes(header)) + _one_stream(compressor)


def dicom_deflated() -> tuple[str, bytes]:
    """Deflated Explicit VR Little Endian: pydicom inflates the whole data set, even to
    read its header; this one holds a 256 MiB private OB element of zeros."""
    from pydicom.dataset import FileMetaDataset
    from pydicom.filewriter import write_file_meta_info

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.2"
    meta.MediaStorageSOPInstanceUID = "1.2.3.4"
    meta.TransferSyntaxUID = "1.2.840.10008.1.2.1.99"
    out = io.BytesIO()
    out.write(bytes(128) + b"DICM")
    write_file_meta_info(out, meta)
    element = struct.pack("<HH2sHI", 0x0011, 0x1010, b"OB", 0, DECLARED)
    compressor = zlib.compressobj(9, zlib.DEFLATED, -zlib.MAX_WBITS)
    head = compressor.compress(element)
    data = _one_stream(compressor, DECLARED)  # deflated DICOM is held to the zip rule, 100:1
    return "bomb.dcm", out.getvalue() + head + data


def gipl_gzip() -> tuple[str, bytes]:
    """GIPL, read only by SimpleITK, gzipped: the catch-all's codecs are capped too."""
    header = bytearray(256)
    struct.pack_into(">4H", header, 0, SIDE, SIDE, SIDE, 1)
    struct.pack_into(">H", header, 8, 15)  # short
    struct.pack_into(">4f", header, 10, 1, 1, 1, 1)
    struct.pack_into(">I", header, 252, 0xEFFFE9B0)
    compressor = zlib.compressobj(9, zlib.DEFLATED, 31)
    return "bomb.gipl.gz", compressor.compress(bytes(header)) + _one_stream(compressor)


BOMBS = {
    "nrrd-bzip2": (nrrd_bzip2, "bzip2"),
    "nrrd-gzip": (nrrd_gzip, "gzip"),
    "nrrd-byte-skip": (nrrd_byte_skip, "bzip2"),
    "metaimage-zlib": (metaimage_zlib, "zlib"),
    "nifti-gzip": (nifti_gzip, "gzip"),
    "dicom-deflate": (dicom_deflated, "deflate"),
    "simpleitk-gipl-gzip": (gipl_gzip, "file data"),
}


@pytest.fixture(scope="module")
def bombs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("bombs")
    made = {}
    for key, (build, _) in BOMBS.items():
        name, body = build()
        assert len(body) < 2 * MiB, (key, len(body))
        (folder / key).mkdir()
        made[key] = folder / key / name
        made[key].write_bytes(body)
    return made


#: Runs ``miss`` and, on the way out, writes the process's peak resident memory (VmHWM:
#: of this program alone, where getrusage's maxrss keeps the forking pytest's) to argv[1].
_MEASURED = """\
import atexit, runpy, sys
from pathlib import Path
where = sys.argv.pop(1)
def peak():
    status = Path("/proc/self/status").read_text().splitlines()
    Path(where).write_text(next(x for x in status if x.startswith("VmHWM:")).split()[1])
atexit.register(peak)
sys.argv[0] = "miss"
runpy.run_module("miss", run_name="__main__", alter_sys=True)
"""


def run_cli(tmp_path: Path, *args: str) -> tuple[int, str, str, int]:
    """``miss ARGS`` in a child: (exit code, stdout, stderr, peak resident memory bytes)."""
    peak = tmp_path / "peak"
    done = subprocess.run(
        [sys.executable, "-c", _MEASURED, str(peak), *args],
        capture_output=True,
        text=True,
        timeout=300,
        stdin=subprocess.DEVNULL,
    )
    return done.returncode, done.stdout, done.stderr, int(peak.read_text()) * 1024


def refused_unread(message: str, key: str) -> None:
    """The refusal says why before anything was decoded: a bomb past the codec's ratio
    (naming the codec), or, for a deflate stream, more than deflate can hold at all."""
    if "cannot hold" in message:  # deflate's own ceiling, 1032:1, said it first
        return
    assert "decompression bomb" in message and BOMBS[key][1] in message, message
    ratio = codecs.ZIP_RATIO if key == "dicom-deflate" else codecs.MAX_RATIO
    assert f"{ratio} times" in message, message


@pytest.mark.parametrize("key", list(BOMBS))
def test_the_cli_refuses_a_bomb_from_its_header(
    key: str, bombs: dict[str, Path], tmp_path: Path
) -> None:
    code, out, err, peak = run_cli(tmp_path, "info", str(bombs[key]))
    assert code == 2, (out, err)
    assert len(err.strip().splitlines()) == 1, err
    assert "Traceback" not in err, err
    refused_unread(err, key)
    # Nothing near the declared 256 MiB was decoded (the CLI itself takes ~40 MB, with
    # SimpleITK's libraries loaded ~130 MB).
    assert peak < DECLARED * 5 // 8, f"peak memory {peak / MiB:.0f} MiB"


def test_convert_refuses_a_bomb_and_writes_nothing(bombs: dict[str, Path], tmp_path: Path) -> None:
    target = tmp_path / "out.stl"
    code, _, err, _ = run_cli(tmp_path, "convert", str(bombs["nrrd-bzip2"]), "-o", str(target))
    assert code == 2 and "decompression bomb" in err, err
    assert not target.exists()


def test_the_caps_leave_real_compressed_scans_alone(datasets: Path) -> None:
    """The real compressed inputs (gzip NIfTI, zlib MetaImage label map at 122:1 under
    the 64 MiB floor, JPEG 2000 DICOM) still read."""
    from miss.io import load_volume

    for name in (
        "nifti/CT_AVM.nii.gz",
        "labels_frogtissue/frogtissue.mhd",
        "ct_abdomen_totalseg/dicom",
        "ct_abdomen_totalseg/example_seg_dicom.nii.gz",
    ):
        assert load_volume(datasets / name).data.size > 0, name


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    folder = tmp_path_factory.mktemp("codec-bombs")
    with serving(folder / "data", folder / "server.log") as running:
        yield running


@pytest.mark.parametrize("key", list(BOMBS))
@pytest.mark.slow
def test_an_upload_of_a_bomb_gets_422_and_nothing_is_kept(
    key: str, bombs: dict[str, Path], server: Server
) -> None:
    before = server.http.get("/api/volumes").json()
    path = bombs[key]
    r = server.http.post("/api/volumes", files={"file": (path.name, path.read_bytes())})
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    refused_unread(detail, key)
    assert server.http.get("/api/volumes").json() == before
    assert list((server.data_dir / "tmp").iterdir()) == []


def test_the_confined_reader_has_a_memory_cap_by_default() -> None:
    """It had the machine's physical memory: now ``MISS_PARSE_MEMORY_MB``, 4096 MB."""
    from miss.server.core.settings import Settings

    limits = Settings.from_env({}).parse_limits()
    assert limits.memory_bytes == 4096 * MiB
    assert Settings.from_env({"MISS_PARSE_MEMORY_MB": "512"}).parse_limits().memory_bytes == (
        512 * MiB
    )
    with pytest.raises(ValueError, match="MISS_PARSE_MEMORY_MB"):
        Settings.from_env({"MISS_PARSE_MEMORY_MB": "-1"})
    assert np.dtype("int16").itemsize * SIDE**3 == DECLARED
