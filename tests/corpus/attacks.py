"""The attack corpus: uploads built to make the server read, or write, what is not theirs.

``attacks(targets)`` returns ``Attack`` records, each an upload (file name and bytes) and
the file outside the upload whose bytes it tries to bring back as voxels. ``targets``
names the files to aim at on the server under test (its database, another volume, a
secret file); ``/proc`` paths are always added. A correct MISS refuses every one with a
4xx and a ``detail``, or stores a volume holding none of the target's bytes.

Used by ``tests/security/test_attack_corpus.py`` and ``benchmarks/robustness.py``.
"""

from __future__ import annotations

import io
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

SIDE = 16  # 16^3 voxels of one byte: a volume that holds 4096 bytes of whatever was read


@dataclass(frozen=True)
class Attack:
    name: str
    filename: str
    content: bytes
    target: Path


def _voxels() -> bytes:
    return (np.arange(SIDE**3) % 251).astype(np.uint8).tobytes()


def mha(lines: list[str], *, ndims: int = 4, newline: str = "\n", local: bool = True) -> bytes:
    """A MetaImage header of bytes (``ndims`` 4 sends it to SimpleITK), ``lines`` last
    before the voxels; ``local`` appends LOCAL voxels."""
    sizes = " ".join([str(SIDE)] * 3 + ["1"] * (ndims - 3))
    head = ["ObjectType = Image", f"NDims = {ndims}", f"DimSize = {sizes}"]
    head += ["ElementType = MET_UCHAR", *lines]
    text = newline.join(head).encode("utf-8") + newline.encode()
    return text + (_voxels() if local else b"")


def _zip(members: dict[str, bytes], links: dict[str, str] | None = None) -> bytes:
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, content in members.items():
            zf.writestr(name, content)
        for name, target in (links or {}).items():
            info = zipfile.ZipInfo(name)
            info.create_system = 3
            info.external_attr = (0o120777 << 16) | 0x20
            zf.writestr(info, target)
    return out.getvalue()


def _nrrd(field: str) -> bytes:
    return (
        "NRRD0004\ntype: uchar\ndimension: 3\n"
        f"sizes: {SIDE} {SIDE} {SIDE}\nencoding: raw\n{field}\n\n"
    ).encode()


#: Ways to spell "read your voxels from FILE" that some reader accepts.
MHA_FORMS = {
    "colon": ["ElementDataFile: {}", "ElementDataFile = LOCAL"],
    "colon no blank": ["ElementDataFile:{}", "ElementDataFile = LOCAL"],
    "tab and blanks": ["  ElementDataFile\t :\t{}", "ElementDataFile = LOCAL"],
    "colon equals": ["ElementDataFile := {}", "ElementDataFile = LOCAL"],
    "equals colon": ["ElementDataFile =: {}", "ElementDataFile = LOCAL"],
    "lower case": ["elementdatafile = {}", "ElementDataFile = LOCAL"],
    "decoy first": ["ElementDataFile = LOCAL", "ElementDataFile = {}"],
    "dot dot": ["ElementDataFile: ../../../../../../../../../..{}", "ElementDataFile = LOCAL"],
    "list": ["ElementDataFile = LIST\n{}"],
    "pattern": ["ElementDataFile = {}%d 1 1 1"],
    "name on next line": ["ElementDataFile\n= {}", "ElementDataFile = LOCAL"],
    "nul in name": ["ElementDataFile\0junk = {}", "ElementDataFile = LOCAL"],
    "lookalike letter": ["ElementDataF\u0456le: {}", "ElementDataFile = LOCAL"],
    "windows drive": ["ElementDataFile = C:{}", ""],
    "long name": ["ElementDataFile: " + "/." * 2000 + "{}", "ElementDataFile = LOCAL"],
}
NRRD_FORMS = {
    "data file": "data file: {}",
    "upper case": "DATA FILE: {}",
    "datafile": "datafile: {}",
    "two fields": "data file: inside.raw\ndatafile: {}",
    "list": "data file: LIST\n{}",
    "pattern": "data file: {}%d 1 1 1",
    "dot dot": "data file: ../../../../../../../../..{}",
}


def attacks(targets: dict[str, Path]) -> list[Attack]:
    """Every attack against every target (``/proc/self/environ`` and ``/proc/1/environ``
    are added to ``targets``)."""
    targets = {**targets, "environ": Path("/proc/self/environ"), "pid 1": Path("/proc/1/environ")}
    found: list[Attack] = []
    for aim, path in targets.items():
        for form, lines in MHA_FORMS.items():
            text = [line.format(path) for line in lines if line]
            for ndims, newline in ((3, "\n"), (4, "\n"), (4, "\r\n"), (4, "\r")):
                body = mha(text, ndims=ndims, newline=newline, local="LOCAL" in text[-1])
                name = f"mha {form} {ndims}-D {newline!r} -> {aim}"
                found.append(Attack(name, "head.mha", body, path))
            detached = mha(text, local=False)
            found.append(Attack(f"mhd in zip {form} -> {aim}", "head.zip",
                                _zip({"scan/head.mhd": detached, "scan/inside.raw": _voxels()}),
                                path))  # fmt: skip
        for form, field in NRRD_FORMS.items():
            body = _zip({"scan/head.nhdr": _nrrd(field.format(path)), "scan/inside.raw": _voxels()})
            found.append(Attack(f"nrrd {form} -> {aim}", "head.zip", body, path))
        link = _zip({"scan/head.mhd": mha(["ElementDataFile = inside.raw"], local=False)},
                    {"scan/inside.raw": str(path)})  # fmt: skip
        found.append(Attack(f"zip with a link -> {aim}", "head.zip", link, path))
        absolute = _zip({str(path).lstrip("/"): b"x", str(path): b"x"})
        found.append(Attack(f"zip member at the path itself -> {aim}", "x.zip", absolute, path))
        escape = _zip({f"../../../../../../..{path}": b"x"})
        found.append(Attack(f"zip member with ../ -> {aim}", "x.zip", escape, path))
    return found


def distinctive(path: Path, pid: int | None = None) -> bytes:
    """32 bytes from the first 4096 of ``path`` (what a 16^3 byte volume holds) that no
    ramp or constant matches by chance; b"" when the file cannot be read or is too short.
    ``/proc/self`` is read as process ``pid`` sees it (the server under test)."""
    if pid is not None and path.parts[:3] == ("/", "proc", "self"):
        path = Path("/proc", str(pid), *path.parts[3:])
    try:
        data = path.read_bytes()[: SIDE**3]
    except OSError:
        return b""
    windows = (data[i : i + 32] for i in range(0, max(len(data) - 32, 0), 8))
    return next((w for w in windows if len(set(w)) >= 8), b"")
