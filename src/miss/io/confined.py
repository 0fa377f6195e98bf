"""Reading untrusted files in a confined child process.

Every reader of uploaded bytes (zips, DICOM, NIfTI, NRRD, MetaImage, label maps, and
SimpleITK's catch-all) runs here, in a child process that

- can read only the Python installation (its libraries) and the upload's own folder,
  and write only inside that folder: Linux **Landlock**, through ``landlockpy``. It
  needs no root and no setup at run time, it is inherited by every thread the readers
  start, and it holds whatever syntax a reader accepts for "read that other file": a
  header that names ``/proc/self/environ``, the database or another user's volume gets
  "permission denied" from the kernel. TCP connect/bind, abstract Unix sockets and
  signals to other processes are refused as well, and UDP and pathname Unix sockets,
  wherever the kernel's Landlock ABI has them (ABI 4, 6, 10 and 9);
- starts with an empty environment (no ``MISS_ADMIN_PASSWORD``, no database URL) and no
  open files but its standard streams;
- has its address space (``RLIMIT_AS``), CPU time, file size and wall-clock time capped
  (memory: ``MISS_PARSE_MEMORY_MB``, 4096 by default, beyond its libraries), and what
  any compressed file may decode to (:mod:`miss.io.codecs`).

The child sends the voxels back as ``out/data.npy`` and everything else as JSON, never
as a pickle, and the parent checks both before it believes them: a reader that a
hostile file took over can lie about what it read, not make the server read more. For
an upload, neither holds the volume whole where the reader streams (a plain NIfTI-1,
DICOM slices): the child writes the file plane by plane, the parent reads it so.

Where Landlock is missing (an old kernel, a container that blocks it), ``probe`` says
why and the server starts anyway, says so in one line, and refuses the formats that can
name other files (detached NRRD and MetaImage headers, and everything only SimpleITK
reads), reading the rest in the same kind of child, unconfined.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from miss.errors import (
    BadParameter,
    DiskFull,
    EmptySurface,
    InputTooLarge,
    MissError,
    UnreadableSegmentation,
    UnreadableVolume,
    UnsafeArchive,
    UnsupportedFormat,
    is_disk_full,
)
from miss.io.common import Streamed
from miss.types import Volume

#: The child's exit codes for "out of memory" and "disk full" (1 is a Python traceback).
EXIT_MEMORY, EXIT_DISK_FULL = 3, 5
#: Where the child leaves what it read, inside the upload's folder.
OUT = "out"
#: Errors the child may report, by name; anything else is "the reader failed".
ERRORS: dict[str, type[MissError]] = {
    cls.__name__: cls
    for cls in (
        BadParameter,
        DiskFull,
        EmptySurface,
        InputTooLarge,
        UnreadableSegmentation,
        UnreadableVolume,
        UnsafeArchive,
        UnsupportedFormat,
    )
}
#: Longest JSON file and error message the parent accepts from the child.
MAX_JSON = 8 << 20
MAX_MESSAGE = 2000
#: numpy dtypes a volume may come back as (no objects, no strings, no structured types).
NUMERIC_KINDS = "biuf"
#: Address space the interpreter and the readers' libraries take before any voxel.
BASE_ADDRESS_SPACE = 3 << 30
#: System folders the dynamic loader and the libraries read (shared objects, time zones).
SYSTEM_READ = (
    "/usr/lib",
    "/usr/lib64",
    "/lib",
    "/lib64",
    "/usr/share/zoneinfo",
    "/etc/ld.so.cache",
)


#: Memory one child may use beyond its libraries by default (``MISS_PARSE_MEMORY_MB``):
#: a 1 GiB volume read whole (a 512 x 512 x 2000 CT) takes about three times that.
DEFAULT_MEMORY = 4 << 30


@dataclass(frozen=True)
class Limits:
    """Caps for one child: wall-clock and CPU seconds, bytes of memory beyond the
    libraries (0: none), bytes it may write (unpacked zip and voxels), bytes a zip, or
    any compressed file, may inflate to (:mod:`miss.io.codecs`), and how much lower than
    its parent's its CPU priority is (a nice increment, 0 to 19)."""

    seconds: float = 600.0
    memory_bytes: int = DEFAULT_MEMORY
    write_bytes: int = 16 << 30
    unzipped_bytes: int = 8 << 30
    min_free_bytes: int = 0
    nice: int = 0


@dataclass(frozen=True)
class Confinement:
    """How uploads are read on this machine: ``mechanism`` when confined, else ``problem``."""

    mechanism: str = ""
    problem: str = ""
    read_roots: tuple[str, ...] = ()

    @property
    def confined(self) -> bool:
        """True when uploads are read confined (a mechanism, no problem)."""
        return bool(self.mechanism) and not self.problem


@dataclass
class Parsed:
    """What the child read: the volume (identity still in ``patient``), or, asked for
    planes (``whole=False``), the same as ``streamed``; the DICOM series it found (mode
    ``series``), or, asked to (``ask_series``), the series to choose among instead of a
    volume (``choices``: the files hold several and none was named), a label table (mode ``labels``). ``close()`` once the planes are read."""

    volume: Volume | None = None
    streamed: Streamed | None = None
    series: list[dict[str, Any]] = field(default_factory=list)
    choices: list[dict[str, Any]] = field(default_factory=list)
    table: list[dict[str, Any]] = field(default_factory=list)
    table_source: str = ""
    source_name: str = ""
    voxel_file: BinaryIO | None = None

    def close(self) -> None:
        """Close the voxel file the planes are read from, if any."""
        if self.voxel_file is not None:
            self.voxel_file.close()


# --------------------------------------------------------------------------- parent side


def read_roots(data_dir: Path) -> tuple[tuple[str, ...], str]:
    """Folders the child must read (the interpreter, its packages, MISS, system libraries)
    and a problem ("" for none): none of them may hold the data folder."""
    import miss

    candidates = {sys.prefix, sys.base_prefix, sys.exec_prefix, sys.base_exec_prefix}
    candidates |= set(_child_path())
    candidates.add(str(Path(miss.__file__).resolve().parent))
    candidates |= set(SYSTEM_READ)
    roots = sorted({os.path.realpath(p) for p in candidates if os.path.exists(p)})
    data = Path(os.path.realpath(data_dir))
    for root in roots:
        if data == Path(root) or Path(root) in data.parents:
            return (), (
                f"the data folder {data} lies inside {root}, which the file readers must be "
                "able to read; move MISS_DATA_DIR out of the Python installation and MISS's "
                "source folder"
            )
    return tuple(roots), ""


def _child_path() -> list[str]:
    """``sys.path`` as the child sees it: isolated mode, so without this process's working
    folder or script folder (which may well hold the data folder), only the standard
    library, site-packages and what their ``.pth`` files add."""
    found = subprocess.run(
        [sys.executable, "-I", "-c", "import json, sys; print(json.dumps(sys.path))"],
        capture_output=True,
        text=True,
        timeout=60,
        env={"PATH": "/usr/bin:/bin"},
    )
    paths = json.loads(found.stdout) if found.returncode == 0 else []
    return [p for p in paths if isinstance(p, str) and os.path.isabs(p)]


def probe(data_dir: Path) -> Confinement:
    """Check that a confined child can read its own folder and nothing else here."""
    roots, problem = read_roots(data_dir)
    if problem:
        return Confinement(problem=problem)
    try:
        import landlockpy
    except ImportError:
        return Confinement(problem="the landlockpy package is not installed")
    abi = landlockpy.abi_version()
    if abi < 1:
        return Confinement(
            problem="this Linux kernel has no Landlock (5.13 or later with Landlock enabled "
            "in its LSM list is needed)"
        )
    work = Path(data_dir) / "tmp" / f"probe-{os.getpid()}"
    outside = Path(data_dir) / "tmp" / f"probe-{os.getpid()}-outside"
    listener = socket.create_server(("127.0.0.1", 0))  # the child must not reach it
    try:
        (work / OUT).mkdir(parents=True, exist_ok=True)
        (work / "inside").write_bytes(b"in")
        outside.write_bytes(b"out")
        port = listener.getsockname()[1]
        config = {"mode": "probe", "outside": str(outside), "roots": list(roots), "port": port}
        proc = _spawn(work, config, Limits(seconds=30))
        answer = _result(work, proc, Limits(seconds=30))
    except MissError as exc:
        return Confinement(problem=f"the confined test child failed ({exc})")
    finally:
        listener.close()
        outside.unlink(missing_ok=True)
        _remove(work)
    if answer.get("inside") != "in" or answer.get("outside") != "denied":
        return Confinement(problem=f"Landlock did not confine the test child ({answer})")
    if abi >= 4 and answer.get("tcp") != "denied":
        return Confinement(problem=f"Landlock let the test child connect over TCP ({answer})")
    version = getattr(landlockpy, "__version__", "?")
    network = ", no TCP" if abi >= 4 else ""
    mechanism = f"Landlock ABI {abi} (landlockpy {version}){network}"
    return Confinement(mechanism=mechanism, read_roots=roots)


def parse_upload(
    work: Path,
    upload: str,
    confinement: Confinement,
    limits: Limits,
    mode: str = "volume",
    series: str | None = None,
    grid: dict[str, Any] | None = None,
    whole: bool = True,
    ask_series: bool = False,
) -> Parsed:
    """Read ``work/upload`` (a zip is unpacked into ``work/unzipped`` first) in a child.

    ``mode``: ``volume`` (one volume; ``series`` picks a DICOM series by its UID in the
    files), ``series`` (list the DICOM series only), ``labels`` (a label map and the
    label table that comes with it) or ``segmentation`` (the one DICOM SEG or RT-STRUCT
    among the files as a label map and its table; an RT-STRUCT is rasterised on ``grid``,
    ``{"affine": 4x4 voxel-to-LPS-mm rows, "dims": [X, Y, Z]}`` of its image series).
    ``whole=False``: the volume as ``Parsed.streamed``, its (X, Y) planes read from the
    child's file one at a time (this process never holds it whole); the caller closes
    the ``Parsed``. ``ask_series``: files that hold several DICOM series and no ``series``
    give ``Parsed.choices``, not the largest. Raises the reader's ``MissError`` as the
    child reported it.
    """
    out = work / OUT
    _remove(out)
    out.mkdir()
    config = {
        "mode": mode,
        "upload": upload,
        "series": series or "",
        "grid": grid or {},
        "roots": list(confinement.read_roots),
        "confined": confinement.confined,
        "unzipped_bytes": limits.unzipped_bytes,
        "min_free_bytes": limits.min_free_bytes,
        "ask_series": ask_series,
    }
    proc = _spawn(work, config, limits)
    answer = _result(work, proc, limits)
    return _parsed(out, answer, whole)


def _spawn(work: Path, config: dict[str, Any], limits: Limits) -> subprocess.Popen[bytes]:
    config = {**config, "memory_bytes": limits.memory_bytes, "write_bytes": limits.write_bytes}
    config["cpu_seconds"] = math.ceil(limits.seconds)
    config["nice"] = limits.nice
    config["package"] = str(Path(__file__).resolve().parent.parent)
    env = {"PATH": "/usr/bin:/bin", "LANG": "C.UTF-8", "OMP_NUM_THREADS": "1"}
    with open(work / "child.log", "ab") as log:
        return subprocess.Popen(
            [sys.executable, "-I", "-c", _BOOTSTRAP, json.dumps(config)],
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=log,
            cwd=work,
            env=env,
            close_fds=True,
            start_new_session=True,
        )


def _result(work: Path, proc: subprocess.Popen[bytes], limits: Limits) -> dict[str, Any]:
    """The child's answer; its failure as a ``MissError`` with a message that says what
    to do (the child's own message when it sent one)."""
    try:
        _wait_unreaped(proc, limits.seconds)
    except subprocess.TimeoutExpired:
        _kill(proc)
        raise UnreadableVolume(
            f"reading the upload took longer than {limits.seconds:g} s and was stopped; "
            "check that it is one scan, or ask the administrator to raise MISS_PARSE_SECONDS."
        ) from None
    except BaseException:
        _kill(proc)
        raise
    # The child has exited; what it started in its process group goes now, while the
    # group's id is still held by the child's unreaped zombie (so no other process can
    # have it), before anything it wrote is read. A descendant that left the group
    # (``setsid``) could outlive this and still write in the folder: the parent reads
    # nothing from it by name after checking it, and never through a map (``_planes``).
    code = _kill(proc)
    answer = _read_json(work / OUT / "result.json")
    if isinstance(answer, dict) and "error" in answer:
        cls = ERRORS.get(str(answer["error"]), UnreadableVolume)
        raise cls(_clean_message(answer.get("message")))
    if code == 0 and isinstance(answer, dict):
        return answer
    raise _crash(code)


def _wait_unreaped(proc: subprocess.Popen[bytes], seconds: float) -> None:
    """Wait until the child exits, leaving it a zombie (its process group stays its own);
    ``subprocess.TimeoutExpired`` after ``seconds``."""
    deadline = time.monotonic() + seconds
    delay = 0.0005
    while not os.waitid(os.P_PID, proc.pid, os.WEXITED | os.WNOWAIT | os.WNOHANG):
        if time.monotonic() > deadline:
            raise subprocess.TimeoutExpired(proc.args, seconds)
        time.sleep(delay)
        delay = min(2 * delay, 0.05)


def _kill(proc: subprocess.Popen[bytes]) -> int:
    """Kill the child's process group (the child and all it started that stayed in it),
    reap the child; its exit code."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)
    return proc.wait()


def _crash(code: int) -> MissError:
    if code in (-signal.SIGXCPU, -signal.SIGKILL):
        return UnreadableVolume(
            "reading the upload took too long and was stopped; check that it is one scan."
        )
    if code == -signal.SIGXFSZ:
        return InputTooLarge(
            "the upload expands to more than the server accepts; send a smaller series."
        )
    if code == EXIT_MEMORY:
        return InputTooLarge("the volume does not fit in the server's memory; upload fewer slices.")
    if code == EXIT_DISK_FULL:
        return DiskFull(
            "disk full: the server's data folder ran out of space while reading this upload, "
            "and nothing of it was kept; ask the administrator to free space there, then send "
            "it again."
        )
    return UnreadableVolume(
        f"the file reader stopped ({_signal_name(code)}) on this upload; the file is damaged "
        "or not a scan: export it again."
    )


def _signal_name(code: int) -> str:
    if code < 0:
        try:
            return signal.Signals(-code).name
        except ValueError:
            return f"signal {-code}"
    return f"exit code {code}"


def _clean_message(message: Any) -> str:
    text = str(message or "the file could not be read")[:MAX_MESSAGE]
    return "".join(c if c.isprintable() else " " for c in text)


def _open_regular(path: Path) -> int:
    """A descriptor on ``path`` only if it is a regular file the child made (no link)."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW)
    except OSError as exc:
        raise UnreadableVolume("the file reader gave no result; the file is damaged.") from exc
    info = os.fstat(fd)
    if not (info.st_mode & 0o170000 == 0o100000 and info.st_nlink == 1):
        os.close(fd)
        raise UnreadableVolume("the file reader gave an unusable result; the file is damaged.")
    return fd


def _read_json(path: Path) -> Any:
    if not path.exists() and not path.is_symlink():
        return None
    with os.fdopen(_open_regular(path), "rb") as f:
        text = f.read(MAX_JSON + 1)
    if len(text) > MAX_JSON:
        raise UnreadableVolume("the file reader's result is too large; the file is damaged.")
    try:
        return json.loads(text)
    except ValueError:
        raise UnreadableVolume("the file reader gave an unusable result.") from None


def _parsed(out: Path, answer: dict[str, Any], whole: bool = True) -> Parsed:
    parsed = Parsed(
        series=_list_of_dicts(answer.get("series")),
        choices=_list_of_dicts(answer.get("choices")),
        table=_list_of_dicts(answer.get("table")),
        table_source=str(answer.get("table_source") or "")[:MAX_MESSAGE],
        source_name=str(answer.get("source_name") or "")[:MAX_MESSAGE],
    )
    if answer.get("volume") and whole:
        parsed.volume = _volume(out, answer["volume"])
    elif answer.get("volume"):
        affine, meta, patient = _described(answer["volume"])
        parsed.voxel_file, shape, dtype = _planes_file(out / "data.npy")
        source_format = str(meta.get("source_format", ""))
        planes = _planes(parsed.voxel_file, shape, dtype)
        parsed.streamed = Streamed(
            shape, dtype, affine, planes, lambda lo, hi: meta, source_format, patient
        )
    return parsed


def _list_of_dicts(value: Any) -> list[dict[str, Any]]:
    return [v for v in value if isinstance(v, dict)] if isinstance(value, list) else []


def _volume(out: Path, described: Any) -> Volume:
    """The volume the child wrote, checked: numeric 3-D voxels of the declared shape, a
    finite 4x4 affine, JSON metadata."""
    affine, meta, patient = _described(described)
    return Volume(_voxels(out / "data.npy"), affine, meta=meta, patient=patient)


def _described(described: Any) -> tuple[np.ndarray, dict[str, Any], dict[str, Any]]:
    """The child's (affine, meta, patient) of the volume it wrote, checked: a 4x4
    affine, JSON objects."""
    if not isinstance(described, dict):
        raise UnreadableVolume("the file reader gave an unusable result.")
    try:
        affine = np.array(described["affine"], dtype=np.float64)
    except (KeyError, TypeError, ValueError):
        raise UnreadableVolume("the file reader gave an unusable geometry.") from None
    if affine.shape != (4, 4):
        raise UnreadableVolume("the file reader gave an unusable geometry.")
    meta, patient = described.get("meta"), described.get("patient")
    meta = meta if isinstance(meta, dict) else {}
    patient = patient if isinstance(patient, dict) else {}
    return affine, meta, patient


def _voxels(path: Path) -> np.ndarray:
    """The child's voxels, checked (:func:`_checked_npy`), read whole."""
    f, shape, fortran, dtype = _checked_npy(path)
    with f:
        flat = np.fromfile(f, dtype=dtype, count=math.prod(shape))
    return flat.reshape(shape, order="F" if fortran else "C")


def _planes_file(path: Path) -> tuple[BinaryIO, tuple[int, int, int], np.dtype]:
    """The child's voxels, checked (:func:`_checked_npy`), open for :func:`_planes`:
    (file, shape, dtype). Fortran order only (what the child writes of a volume), in
    which each (X, Y) plane is one run of bytes."""
    f, shape, fortran, dtype = _checked_npy(path)
    if not fortran:
        f.close()
        raise UnreadableVolume("the file reader gave unusable voxels.")
    x, y, z = (int(n) for n in shape)
    return f, (x, y, z), dtype


def _checked_npy(path: Path) -> tuple[BinaryIO, tuple[int, ...], bool, np.dtype]:
    """The child's ``data.npy`` open at its first voxel, once it is known to be a regular
    file of its own (no link), an ``np.save`` header of numeric 3-D voxels, and exactly
    as long as that header says: (file, shape, Fortran order, dtype).

    Its name is removed at once: the descriptor is all this process reads from, so a
    file put in its place later is never seen; its disk space comes back on ``close``.
    """
    f = os.fdopen(_open_regular(path), "rb")
    path.unlink()
    try:
        try:
            version = np.lib.format.read_magic(f)
            read_header = _NPY_HEADERS.get(version)
            if read_header is None:
                raise ValueError(f"npy version {version}")
            shape, fortran, dtype = read_header(f)
        except (ValueError, SyntaxError, TypeError):
            raise UnreadableVolume("the file reader gave unusable voxels.") from None
        if dtype.kind not in NUMERIC_KINDS or dtype.hasobject or len(shape) != 3:
            raise UnreadableVolume("the file reader gave unusable voxels.")
        if os.fstat(f.fileno()).st_size - f.tell() != math.prod(shape) * dtype.itemsize:
            raise UnreadableVolume("the file reader gave truncated voxels.")
    except BaseException:
        f.close()
        raise
    return f, shape, fortran, dtype


def _planes(f: BinaryIO, shape: tuple[int, int, int], dtype: np.dtype) -> Iterator[np.ndarray]:
    """The (X, Y) planes, z in order, of the checked Fortran-order file ``f`` (at its first
    voxel), one in memory at a time.

    Read with ``pread`` from the checked descriptor, not mapped: a map's pages would all
    stay resident in this process as they are read, and a file truncated under a map
    (by a descendant of the child that escaped its process group) kills the server with
    SIGBUS, where a short read here is refused. Non-finite values are refused too: the
    readers replace NaN, so only a reader that lies sends one.
    """
    x, y, z = shape
    size, start = x * y * dtype.itemsize, f.tell()
    for k in range(z):
        buffer = bytearray(size)
        view, got = memoryview(buffer), 0
        while got < size and (n := os.preadv(f.fileno(), [view[got:]], start + k * size + got)):
            got += n
        if got < size:
            raise UnreadableVolume("the file reader gave truncated voxels.")
        plane = np.frombuffer(buffer, dtype=dtype).reshape((x, y), order="F")
        if dtype.kind == "f" and not np.isfinite(plane).all():
            raise UnreadableVolume("the file reader gave voxels that are not numbers.")
        yield plane


#: The .npy header versions ``np.save`` writes (3.0 only for non-Latin-1 field names).
_NPY_HEADERS = {
    (1, 0): np.lib.format.read_array_header_1_0,
    (2, 0): np.lib.format.read_array_header_2_0,
}


def _remove(path: Path) -> None:
    import shutil

    shutil.rmtree(path, ignore_errors=True)


# --------------------------------------------------------------------------- child side

#: The child's first lines: limits, then Landlock, and only then any reader is imported,
#: so every thread a library starts is confined too. ``miss/__init__`` (VTK, numba) is
#: not run: a bare package module stands in for it.
_BOOTSTRAP = """\
import json, sys, types
config = json.loads(sys.argv[1])
package = types.ModuleType("miss")
package.__path__ = [config["package"]]
sys.modules["miss"] = package
from miss.io import confined
sys.exit(confined.child_main(config))
"""


def child_main(config: dict[str, Any]) -> int:
    """Entry point of the child: cap, confine, read, write ``out/``; exit code 0, else
    ``EXIT_MEMORY`` or ``EXIT_DISK_FULL`` (anything else: the parent reports a crash)."""
    _cap(config)
    if config.get("confined", True) or config["mode"] == "probe":
        _confine(config["roots"], Path.cwd())
    from miss.io import codecs

    codecs.set_max_decoded(int(config.get("unzipped_bytes") or 0))
    out = Path.cwd() / OUT
    try:
        answer = _CHILD_MODES[config["mode"]](config)
    except MemoryError:
        return EXIT_MEMORY
    except MissError as exc:
        answer = {"error": type(exc).__name__, "message": str(exc)}
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        return EXIT_DISK_FULL
    try:
        _write_json(out / "result.json", answer)
    except OSError as exc:
        if not is_disk_full(exc):
            raise
        return EXIT_DISK_FULL
    return 0


def _cap(config: dict[str, Any]) -> None:
    import resource

    def limit(which: int, value: int) -> None:
        with contextlib.suppress(ValueError, OSError):
            resource.setrlimit(which, (value, value))

    limit(resource.RLIMIT_CORE, 0)
    if config.get("nice"):
        os.nice(int(config["nice"]))
    limit(resource.RLIMIT_CPU, int(config.get("cpu_seconds", 600)))
    if config.get("memory_bytes"):
        limit(resource.RLIMIT_AS, int(config["memory_bytes"]) + BASE_ADDRESS_SPACE)
    if config.get("write_bytes"):
        limit(resource.RLIMIT_FSIZE, int(config["write_bytes"]))


def _confine(roots: list[str], work: Path) -> None:
    """Landlock: read (and map) ``roots``, everything inside ``work``, nothing else."""
    from landlockpy import AccessFS, AccessNet, Ruleset, Scope, abi_version, fs_for_abi

    abi = abi_version()
    if abi < 1:
        raise SystemExit(4)  # the parent asked for confinement: never read unconfined
    everything = fs_for_abi(abi)
    read = AccessFS.READ_FILE | AccessFS.READ_DIR | AccessFS.EXECUTE
    with Ruleset(
        handled_fs=everything,
        # UDP from ABI 10, and (in ``everything``) pathname Unix sockets from ABI 9: taken
        # where the kernel has them, dropped where it does not (best effort).
        handled_net=AccessNet.BIND_TCP
        | AccessNet.CONNECT_TCP
        | AccessNet.BIND_UDP
        | AccessNet.CONNECT_SEND_UDP,
        scoped=Scope.ABSTRACT_UNIX_SOCKET | Scope.SIGNAL,
    ) as rules:
        for root in roots:
            rights = read if os.path.isdir(root) else AccessFS.READ_FILE | AccessFS.EXECUTE
            rules.allow_path(root, rights & everything)
        rules.allow_path(str(work), everything)
        rules.restrict()


def _probe(config: dict[str, Any]) -> dict[str, Any]:
    def attempt(path: str) -> str:
        try:
            with open(path) as f:
                return f.read()
        except PermissionError:
            return "denied"
        except OSError as exc:
            return f"error {exc.errno}"

    def connect(port: int) -> str:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=5).close()
        except PermissionError:
            return "denied"
        except OSError as exc:
            return f"error {exc.errno}"
        return "connected"

    return {
        "inside": attempt("inside"),
        "outside": attempt(config["outside"]),
        "tcp": connect(int(config["port"])),
    }


def _source(config: dict[str, Any]) -> Path:
    """The upload, or what to read from it once unpacked (a zip, once per folder)."""
    from miss.io.archive import pick_source

    unpacked = _unpack(config)
    return pick_source(unpacked) if unpacked.is_dir() else unpacked


def _unpack(config: dict[str, Any]) -> Path:
    """The upload file, or the folder ``unzipped`` (a zip upload is unpacked there; the
    files of an upload of several are gathered there)."""
    from miss.io.archive import extract_zip, is_zip

    work = Path.cwd()
    unpacked = work / "unzipped"
    upload = work / config["upload"]
    if upload.is_file() and is_zip(upload):
        unpacked.mkdir(exist_ok=True)
        extract_zip(upload, unpacked, int(config["unzipped_bytes"]), _free_space_check(config))
        upload.unlink()  # halve the disk the upload takes meanwhile
    return unpacked if unpacked.is_dir() else upload


def _free_space_check(config: dict[str, Any]) -> Any:
    minimum = int(config.get("min_free_bytes") or 0)

    def check(_written: int) -> None:
        stat = os.statvfs(".")
        if minimum and stat.f_bavail * stat.f_frsize < minimum:
            raise DiskFull(
                "disk full: the server's data folder ran out of space while unpacking this "
                "zip, and nothing of it was kept; ask the administrator to free space there."
            )

    return check


def _read(config: dict[str, Any]) -> dict[str, Any]:
    from miss.io import load_volume

    source = _source(config)
    if not config.get("confined", True):
        _refuse_pointers(source)
    series = config.get("series") or None
    if config.get("ask_series") and series is None:
        choices = _several_series(source)
        if choices:
            return {"choices": _jsonable(choices), "source_name": _relative(source)}
    described = _stream_volume(source, series)
    if described is None:
        described = _write_volume(load_volume(source, series=series))
    return {"volume": described, "source_name": _relative(source)}


def _several_series(source: Path) -> list[dict[str, Any]]:
    """The DICOM series in the folder ``source`` when it holds more than one (as
    :func:`miss.io.list_series` gives them, every patient's identity cut out of their
    descriptions: a zip may mix patients), else none: one series, or no DICOM, or files
    whose headers do not list, which reading them then diagnoses."""
    from miss.deid import identity_values, scrub
    from miss.io import dicom

    if not source.is_dir():
        return []
    try:
        listed, patient = dicom.list_series_identity(source)
    except Exception:  # noqa: BLE001 - the read that follows says what is wrong
        return []
    values = identity_values(patient)
    for entry in listed:
        entry["description"] = scrub(str(entry.get("description") or ""), values)
    return listed if len(listed) > 1 else []


def _stream_volume(source: Path, series: str | None) -> dict[str, Any] | None:
    """Write what ``load_volume`` would read plane by plane, when its reader streams
    (:func:`miss.io.stream_volume`), so this process never holds the volume; None when
    it must be read whole: not streamable, NaN voxels (``NotStreamable``), or any failure,
    which the whole read then reports as ``load_volume`` would."""
    from miss.io import stream_volume

    written = Path(OUT) / "data.npy"
    try:
        streamed = stream_volume(source, series)
        if streamed is None:
            return None
        lo, hi = _write_planes(written, streamed.dims, np.dtype(streamed.dtype), streamed.planes)
    except OSError as exc:
        if is_disk_full(exc):
            raise
        written.unlink(missing_ok=True)
        return None
    except Exception:  # noqa: BLE001 - the whole read gives the diagnosis (or the volume)
        written.unlink(missing_ok=True)
        return None
    described = {"affine": streamed.affine.tolist(), "meta": streamed.meta(lo, hi)}
    return _jsonable(described | {"patient": streamed.patient})


def _write_planes(
    path: Path, dims: tuple[int, int, int], dtype: np.dtype, planes: Iterator[np.ndarray]
) -> tuple[float, float]:
    """Write (X, Y) planes, z in order, as the .npy file ``np.save`` writes of the
    Fortran-order volume (same header, same bytes), one plane in memory at a time;
    returns the values' (min, max). Plain writes, not a writable map: the pages of a map
    would stay in this process's resident memory until it is closed, all of them."""
    header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": True}
    lo, hi, count = math.inf, -math.inf, 0
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, header | {"shape": tuple(dims)})
        for plane in planes:
            if plane.shape != tuple(dims[:2]) or plane.dtype != dtype:
                raise ValueError(f"plane {count} is {plane.shape} {plane.dtype}")
            f.write(np.ascontiguousarray(plane.T).data)  # x fastest, as Fortran order
            lo, hi = min(lo, float(plane.min())), max(hi, float(plane.max()))
            count += 1
    if count != dims[2]:
        raise ValueError(f"{count} planes of {dims[2]}")
    return lo, hi


def _series(config: dict[str, Any]) -> dict[str, Any]:
    from miss.io import list_series

    source = _source(config)
    if not config.get("confined", True):
        _refuse_pointers(source)
    return {"series": _jsonable(list_series(source))}


def _labels(config: dict[str, Any]) -> dict[str, Any]:
    from miss.structures.labels import find_label_table

    answer = _read(config)
    found = find_label_table(Path.cwd() / config["upload"])
    if found:
        table, where = found
        answer["table"] = [
            {"label": k, "name": v.name, "color": list(v.color or ()), "opacity": v.opacity}
            for k, v in table.items()
        ]
        answer["table_source"] = where
    return answer


def _segmentation(config: dict[str, Any]) -> dict[str, Any]:
    """A DICOM SEG or RT-STRUCT (the upload, or the one among the unpacked files) as a
    label map; an RT-STRUCT on ``config["grid"]``. DICOM names no other file, so this
    reads alike confined or not."""
    from miss.io.dicom_seg import find_segmentation, read_rtstruct, read_seg, segmentation_kind

    found = _unpack(config)
    source = find_segmentation(found) if found.is_dir() else found
    if segmentation_kind(source) == "rtstruct":
        labels, table = read_rtstruct(source, _grid(config.get("grid")))
    else:  # read_seg says what else it is
        labels, table = read_seg(source)
    rows = [{"label": k, "name": v.name, "color": list(v.color or ())} for k, v in table.items()]
    return {
        "volume": _write_volume(labels),
        "table": rows,
        "table_source": labels.meta.get("source_format", ""),
        "source_name": _relative(source),
    }


def _grid(described: Any) -> Volume:
    """The image grid an RT-STRUCT is drawn on, as a Volume without voxels (a read-only
    zero-stride view of one 0: only its dims and affine are used)."""
    try:
        affine = np.array(described["affine"], dtype=np.float64)
        dims = tuple(int(d) for d in described["dims"])
    except (KeyError, TypeError, ValueError):
        raise BadParameter(
            "an RT-STRUCT is drawn on its image series: give the series' grid "
            "({affine, dims}) with it."
        ) from None
    if affine.shape != (4, 4) or len(dims) != 3 or min(dims) < 1:
        raise BadParameter("the image grid needs a 4x4 affine and three positive dims.")
    return Volume(np.broadcast_to(np.zeros(1, np.uint8), dims), affine)


def _refuse_pointers(source: Path) -> None:
    """Unconfined, only formats that cannot name another file are read."""
    from miss.io import self_contained

    problem = self_contained(source)
    if problem:
        raise UnsupportedFormat(
            f"{problem}; this server cannot confine its file readers, so formats that name "
            "other files are refused: upload a .zip of DICOM files, a .nii/.nii.gz, an .nrrd "
            "with its data inside, or an .mha with LOCAL data."
        )


def _relative(source: Path) -> str:
    try:
        return str(source.relative_to(Path.cwd()))
    except ValueError:
        return source.name


def _write_volume(volume: Volume) -> dict[str, Any]:
    np.save(Path(OUT) / "data.npy", np.asfortranarray(volume.data), allow_pickle=False)
    return _jsonable(
        {"affine": volume.affine.tolist(), "meta": volume.meta, "patient": volume.patient}
    )


def _jsonable(value: Any) -> Any:
    return json.loads(
        json.dumps(value, default=lambda o: o.item() if hasattr(o, "item") else str(o))
    )


def _write_json(path: Path, value: Any) -> None:
    path.write_text(json.dumps(value))


_CHILD_MODES = {
    "probe": _probe,
    "volume": _read,
    "series": _series,
    "labels": _labels,
    "segmentation": _segmentation,
}
