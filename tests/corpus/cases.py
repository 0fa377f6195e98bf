"""The bad-input corpus: every case written from code into a folder, never checked in.

``generate(dest)`` writes all cases below ``dest`` and returns them as ``Case``
records. ``expect`` says what a correct MISS does with each:

- ``"error"``: refused with a ``MissError`` subclass (CLI exit 2, HTTP 4xx) whose message
  names the problem and the fix;
- ``"ok"``: loaded as a ``Volume`` with finite voxels and a non-degenerate affine (the
  reader may note what it assumed or dropped).

``why`` gives the reason for the expectation. Folders are DICOM series (zip them to
upload); other cases are single files, or a file inside a folder when it needs a
companion (``.nhdr`` + ``.raw``). Run ``python tests/corpus/cases.py OUT`` to write
the corpus into ``OUT`` and list it.
"""

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

if __package__ in (None, ""):  # run as a script or loaded by path: make ``corpus`` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

Kind = Literal["dicom", "nifti", "nrrd", "mha", "zip", "other"]
Expect = Literal["error", "ok"]


@dataclass(frozen=True)
class Case:
    """One corpus input: ``path`` is a file, a folder (DICOM series) or a ``.zip``."""

    name: str
    path: Path
    kind: Kind
    expect: Expect
    why: str = ""


class Writer:
    """Writes case inputs under ``dest`` and records them; names must be unique slugs."""

    def __init__(self, dest: Path) -> None:
        self.dest = dest
        self.cases: list[Case] = []

    def file(
        self, name: str, suffix: str, content: bytes, kind: Kind, expect: Expect, why: str
    ) -> Path:
        """A single-file case ``dest/name+suffix``."""
        path = self.dest / f"{name}{suffix}"
        path.write_bytes(content)
        self.add(name, path, kind, expect, why)
        return path

    def folder(self, name: str, kind: Kind, expect: Expect, why: str, inside: str = "") -> Path:
        """A case folder ``dest/name``; the case's path is ``inside`` it when given."""
        folder = self.dest / name
        folder.mkdir(parents=True)
        self.add(name, folder / inside if inside else folder, kind, expect, why)
        return folder

    def add(self, name: str, path: Path, kind: Kind, expect: Expect, why: str) -> None:
        if any(c.name == name for c in self.cases):
            raise ValueError(f"duplicate corpus case name {name!r}")
        self.cases.append(Case(name, path, kind, expect, why))


def generate(dest: Path) -> list[Case]:
    """Write every corpus case below ``dest`` (created if needed; must not hold a corpus)."""
    from corpus import bad_dicom, bad_files, bad_nifti, bad_nrrd_mha, bad_zip

    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    writer = Writer(dest)
    for module in (bad_dicom, bad_zip, bad_nifti, bad_nrrd_mha, bad_files):
        module.write(writer)
    return writer.cases


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: python tests/corpus/cases.py OUT_FOLDER")
    for case in generate(Path(sys.argv[1])):
        print(f"{case.expect:5}  {case.kind:5}  {case.name:40}  {case.path}")
