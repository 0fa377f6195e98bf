"""Mutation fuzzing of the readers: small valid files, damaged byte by byte.

A case is a seed format and a short list of mutations (:data:`Op`); :func:`apply`
turns the seed's bytes into the damaged input, :func:`run_case` writes it and calls
``load_volume``. The property every reader must keep: a ``Volume`` that passes
:func:`corpus.checks.volume_problems`, or a ``MissError`` - never another exception,
never a hang, never a dead process.

The hypothesis test (tests/test_fuzz_readers.py) draws the mutations; :func:`fuzz_readers`
draws them from a seeded ``random.Random`` for a longer run in a worker process (so that
a native crash is counted, not fatal), for ``benchmarks/robustness.py``::

    python tests/corpus/fuzz.py SECONDS [SEED]
"""

from __future__ import annotations

import gzip
import json
import random
import re
import signal
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path

if __package__ in (None, ""):  # run as a script or loaded by path: make ``corpus`` importable
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from corpus import files  # noqa: E402
from corpus.checks import volume_problems  # noqa: E402

#: A mutation: (kind, position, value). Positions are taken modulo the input's length.
Op = tuple[str, int, int]
KINDS = ("flip", "byte", "word", "cut", "insert", "delete", "number")
#: Integers that break sizes and offsets when written over binary fields.
WORDS = (
    0,
    1,
    2,
    0x7F,
    0x80,
    0xFF,
    0x7FFF,
    0x8000,
    0xFFFF,
    0x7FFFFFFF,
    0x80000000,
    0xFFFFFFFF,
    348,
    352,
)
#: Text that breaks numbers in text headers (NRRD, MetaImage, DICOM DS/IS values).
NUMBERS = (
    b"0",
    b"-1",
    b"1e308",
    b"nan",
    b"inf",
    b"4294967296",
    b"99999999999999999999",
    b"",
    b"x",
    b"1 2 3 4 5",
    b"0.0",
    b"100000",
)
#: How far into the input text numbers are looked for (the header).
HEADER_SPAN = 2048
#: Per-case time limit of the worker loop, seconds (a reader slower than this hangs).
CASE_SECONDS = 30


@cache
def seeds() -> dict[str, bytes]:
    """The valid inputs mutations start from, by format."""
    slices = [files.dicom_bytes(files.dicom_slice(k)) for k in range(3)]
    return {
        "dicom": slices[1],  # the middle slice of a 3-slice series; the others stay intact
        "nifti": files.nifti_bytes(),
        "nifti-gz": files.nifti_bytes(gz=True),
        "nifti-gz-inner": files.nifti_bytes(),  # mutated, then gzipped
        "nrrd": files.nrrd_bytes(),
        "nrrd-gzip": files.nrrd_bytes(encoding="gzip"),
        "nhdr": files.nrrd_bytes().split(b"\n\n")[0] + b"\ndata file: volume.raw\n",
        "mha": files.mha_bytes(),
        "mhd": files.mha_header(files.SHAPE, "volume.raw").encode(),
        "zip": files.zip_bytes({f"series/IM{k + 1}.dcm": s for k, s in enumerate(slices)}),
    }


#: The formats the hypothesis test covers (the brief's six); the loop covers all seeds.
CORE = ("dicom", "nifti", "nifti-gz", "nrrd", "mha", "zip")


def apply(data: bytes, ops: list[Op]) -> bytes:
    """``data`` with each mutation applied in turn."""
    out = bytearray(data)
    for kind, position, value in ops:
        at = position % (len(out) + 1)
        if kind == "flip" and out:
            out[at % len(out)] ^= 1 << (value % 8)
        elif kind == "byte" and out:
            out[at % len(out)] = value % 256
        elif kind == "word":  # a 2-, 4- or 8-byte little-endian integer over a field
            width = (2, 4, 8)[value % 3]
            word = WORDS[(value // 3) % len(WORDS)] % (1 << (8 * width))
            out[at : at + width] = word.to_bytes(width, "little")
        elif kind == "cut":
            del out[at:]
        elif kind == "insert":
            out[at:at] = bytes([value % 256]) * (1 + value % 64)
        elif kind == "delete":
            del out[at : at + 1 + value % 64]
        elif kind == "number":
            out = bytearray(_renumber(bytes(out), position, NUMBERS[value % len(NUMBERS)]))
    return bytes(out)


def _renumber(data: bytes, index: int, replacement: bytes) -> bytes:
    """Replace the ``index``-th number in the header span by ``replacement``."""
    found = list(re.finditer(rb"-?\d+(\.\d+)?", data[:HEADER_SPAN]))
    if not found:
        return data
    match = found[index % len(found)]
    return data[: match.start()] + replacement + data[match.end() :]


def write_case(folder: Path, fmt: str, ops: list[Op]) -> Path:
    """Write the mutated seed (and its intact companions) into ``folder``; the path to load."""
    for old in folder.iterdir():
        old.unlink()
    data = apply(seeds()[fmt], ops)
    if fmt == "dicom":
        for k in (0, 2):
            (folder / f"IM{k + 1}.dcm").write_bytes(files.dicom_bytes(files.dicom_slice(k)))
        (folder / "IM2.dcm").write_bytes(data)
        return folder
    if fmt == "nifti-gz-inner":
        data = gzip.compress(data, mtime=0)
    if fmt in ("nhdr", "mhd"):
        (folder / "volume.raw").write_bytes(files.ramp().astype("<i2").tobytes(order="F"))
    name = {
        "nifti": "v.nii",
        "nifti-gz": "v.nii.gz",
        "nifti-gz-inner": "v.nii.gz",
        "nrrd": "v.nrrd",
        "nrrd-gzip": "v.nrrd",
        "nhdr": "v.nhdr",
        "mha": "v.mha",
        "mhd": "v.mhd",
        "zip": "v.zip",
    }[fmt]
    (folder / name).write_bytes(data)
    return folder / name


def outcome(path: Path) -> tuple[str, str]:
    """("loaded" | "refused" | "bad volume" | "crash", detail) for one input."""
    from miss.errors import MissError
    from miss.io import load_volume

    try:
        vol = load_volume(path)
    except MissError as exc:
        return "refused", str(exc)
    except Exception as exc:  # the finding: anything else escaping a reader
        return "crash", f"{type(exc).__name__}: {exc}"
    problems = volume_problems(vol)
    return ("bad volume", "; ".join(problems)) if problems else ("loaded", "")


def random_case(seed: int, index: int) -> tuple[str, list[Op]]:
    """Case ``index`` of the run ``seed``: a format and 1-4 mutations, reproducibly."""
    rng = random.Random(f"{seed}:{index}")
    fmt = rng.choice(sorted(seeds()))
    ops = [
        (rng.choice(KINDS), rng.randrange(1 << 16), rng.randrange(1 << 16))
        for _ in range(rng.randint(1, 4))
    ]
    return fmt, ops


class Hang(Exception):
    """A case ran longer than ``CASE_SECONDS``."""


@contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    def expire(signum: int, frame: object) -> None:
        raise Hang(f"still running after {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


def _worker(seed: int, start: int, deadline: float) -> None:
    """Run cases ``start``, ``start + 1`` ... until ``deadline``; one JSON line each.

    The index is printed before the case runs, so the parent knows which case killed
    the process if one does. Warnings are errors, as in the test suite: a warning that
    escapes a reader would be a stray line on the command line's stderr.
    """
    warnings.simplefilter("error")
    warnings.filterwarnings("ignore", category=DeprecationWarning, module="pydicom")
    warnings.filterwarnings("ignore", category=ResourceWarning)
    with tempfile.TemporaryDirectory(prefix="miss-fuzz-") as tmp:
        folder = Path(tmp)
        index = start
        while time.time() < deadline:
            fmt, ops = random_case(seed, index)
            print(json.dumps({"start": index}), flush=True)
            try:
                with time_limit(CASE_SECONDS):
                    result, detail = outcome(write_case(folder, fmt, ops))
            except Hang as exc:
                result, detail = "hang", str(exc)
            print(
                json.dumps(
                    {
                        "index": index,
                        "format": fmt,
                        "ops": ops,
                        "result": result,
                        "detail": detail[:300],
                    }
                ),
                flush=True,
            )
            index += 1


def fuzz_readers(seconds: float, seed: int) -> dict:
    """Fuzz every reader for about ``seconds``; counts of what happened.

    Returns
    -------
    dict
        ``cases``, ``loaded``, ``refused`` (a ``MissError``), ``crashes`` (what went wrong
        -> count: an exception type, ``"bad volume"``, ``"hang"``, or ``"native (signal
        N)"`` when the worker process died), ``examples`` (one reproducer per crash kind:
        format, ops, detail; replay with ``write_case``), ``by_format`` and ``seconds``.
    """
    started = time.time()
    tally = _Tally()
    index = 0
    while time.time() < started + seconds:
        index = _run_worker(seed, index, started + seconds, tally)
    return tally.summary(time.time() - started)


class _Tally:
    def __init__(self) -> None:
        self.results: Counter[str] = Counter()
        self.crashes: Counter[str] = Counter()
        self.by_format: Counter[str] = Counter()
        self.examples: dict[str, dict] = {}

    def add(self, fmt: str, ops: list, result: str, detail: str) -> None:
        self.by_format[fmt] += 1
        self.results["crash" if result not in ("loaded", "refused") else result] += 1
        if result in ("loaded", "refused"):
            return
        kind = detail.split(":")[0] if result == "crash" else result
        self.crashes[kind] += 1
        self.examples.setdefault(kind, {"format": fmt, "ops": ops, "detail": detail})

    def summary(self, seconds: float) -> dict:
        return {
            "cases": sum(self.results.values()),
            "loaded": self.results["loaded"],
            "refused": self.results["refused"],
            "crashes": dict(self.crashes),
            "examples": self.examples,
            "by_format": dict(self.by_format),
            "seconds": round(seconds, 1),
        }


def _run_worker(seed: int, index: int, deadline: float, tally: _Tally) -> int:
    """One worker process from case ``index``; returns the next case to run."""
    proc = subprocess.Popen(
        [sys.executable, __file__, "--worker", str(seed), str(index), repr(deadline)],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    assert proc.stdout is not None
    killed, finished, last_line = threading.Event(), threading.Event(), [time.monotonic()]

    def watch() -> None:  # a case stuck in native code, where the worker's alarm cannot fire
        while not finished.wait(1.0):
            if time.monotonic() - last_line[0] > 2 * CASE_SECONDS:
                killed.set()
                proc.kill()
                return

    threading.Thread(target=watch, daemon=True).start()
    running = None
    for line in proc.stdout:
        last_line[0] = time.monotonic()
        record = json.loads(line)
        if "start" in record:
            running = record["start"]
            continue
        running, index = None, record["index"] + 1
        tally.add(record["format"], record["ops"], record["result"], record["detail"])
    finished.set()
    code = proc.wait()
    if running is None:
        return index
    fmt, ops = random_case(seed, running)  # the worker died inside this case
    kind = (
        "hang"
        if killed.is_set()
        else f"native (signal {-code})"
        if code < 0
        else f"native (exit {code})"
    )
    tally.add(fmt, ops, kind, kind)
    return running + 1


if __name__ == "__main__":
    if sys.argv[1:2] == ["--worker"]:
        _worker(int(sys.argv[2]), int(sys.argv[3]), float(sys.argv[4]))
    elif len(sys.argv) in (2, 3):
        print(
            json.dumps(
                fuzz_readers(float(sys.argv[1]), int(sys.argv[2]) if len(sys.argv) == 3 else 0),
                indent=2,
            )
        )
    else:
        sys.exit("usage: python tests/corpus/fuzz.py SECONDS [SEED]")
