"""Robustness: the bad-input corpus and fuzzing against every surface that takes input.

    .venv/bin/python benchmarks/robustness.py [--seconds 30] [--seed 7]

The corpus (``tests/corpus/cases.py``, written into a temporary folder) goes through

- **readers**: ``miss.load_volume`` in this process; a ``MissError`` is a clean refusal;
- **CLI**: ``miss info PATH`` in a fresh process each (2 at a time); exit 2 with one line
  on stderr is a clean refusal, exit 0 an accepted case, anything else (or a traceback)
  a crash;
- **upload API**: ``POST /api/volumes`` of a real ``miss serve`` (folders zipped); a 4xx
  with a ``detail`` string is a clean refusal, a 201 an accepted case (deleted again);
- **attack corpus**: ``tests/corpus/attacks.py`` through the same upload API: headers and
  zips that name the server's database, another account's volume, a secret file or
  ``/proc`` paths; "bytes from outside the upload served" counts bytes of those files
  found in what was stored (must be 0);

then, for ``--seconds`` each,

- **JSON API fuzz**: random and near-valid JSON bodies (NaN, Infinity, huge integers,
  nesting, unicode, wrong content types, raw bytes) to the model, label, share, login and
  user endpoints and random query values to slices and room replays, same server;
- **reader fuzz**: ``fuzz_readers(seconds, seed)`` of ``tests/corpus/fuzz.py`` (mutated
  files through the readers), when that module is there.

"Mismatch" counts corpus cases answered against their ``expect`` (an error case accepted,
an ok case refused). Peak RSS is the high-water mark (``VmHWM``) of the process doing the
work during that row: this one for readers and reader fuzz, the largest ``miss info`` for
the CLI, the server for the API rows. Writes ``results/robustness.{json,md}``; exits 1 on
any 5xx or crash.
"""

from __future__ import annotations

import argparse
import gzip
import json
import random
import resource
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import httpx
import numpy as np
from common import markdown_table, peak_since, save, start_peak
from load import PASSWORD, log_in, start_server, submit, wait_done

import miss
from miss.errors import MissError
from miss.server.storage import chunked

TESTS = Path(__file__).resolve().parents[1] / "tests"
sys.path.insert(0, str(TESTS))
MB = 2**20
TIMEOUT = 120.0


@dataclass
class Row:
    """One surface's counts."""

    surface: str
    tried: int = 0
    refused: int = 0
    accepted: int = 0
    server_errors: int = 0
    crashes: int = 0
    mismatches: int = 0
    peak_mb: float = 0.0
    seconds: float = 0.0
    outside_bytes: int = 0
    notes: list[str] = field(default_factory=list)

    def crash(self, what: str) -> None:
        self.crashes += 1
        self.notes.append(what[:400])

    def cells(self) -> list[Any]:
        return [self.surface, self.tried, self.refused, self.accepted, self.server_errors,
                self.crashes, self.mismatches, self.outside_bytes, round(self.peak_mb),
                round(self.seconds)]  # fmt: skip


HEADER = ["surface", "cases tried", "clean refusals", "accepted OK", "5xx",
          "crashes / tracebacks", "corpus mismatches", "bytes from outside the upload served",
          "peak RSS MB", "seconds"]  # fmt: skip


# -- the corpus ----------------------------------------------------------------------------


def corpus(dest: Path) -> list[Any]:
    from corpus.cases import generate

    return generate(dest)


def mismatch(row: Row, case: Any, accepted: bool, said: str) -> None:
    if accepted != (case.expect == "ok"):
        row.mismatches += 1
        row.notes.append(f"{case.name}: expected {case.expect}, got {said[:200]}")


def readers_row(cases: list[Any]) -> Row:
    """Every case through ``load_volume`` in a child process (this script with
    ``--readers-child``), so that a native crash in a reader is counted, named and
    survived: the child starts again after the case that killed it."""
    row = Row("readers (load_volume)")
    t0, start, peak = time.perf_counter(), 0, 0
    while start < len(cases):
        proc = subprocess.Popen(
            [sys.executable, "-X", "faulthandler", __file__, "--readers-child"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            errors="replace",
        )  # fmt: skip
        todo = [str(c.path) for c in cases[start:]]
        out, err = proc.communicate(json.dumps(todo))
        for line in out.splitlines():
            done = json.loads(line)
            _count_read(row, cases[start], done["result"], done["said"])
            peak, start = max(peak, done["peak"]), start + 1
        if proc.returncode != 0 and start < len(cases):
            row.tried += 1
            row.crash(f"{cases[start].name}: the reader killed the process ({proc.returncode}): "
                      + " | ".join(err.strip().splitlines()[-6:]))  # fmt: skip
            start += 1
    row.seconds = time.perf_counter() - t0
    row.peak_mb = peak / MB
    return row


def _count_read(row: Row, case: Any, result: str, said: str) -> None:
    row.tried += 1
    if result == "refused":
        row.refused += 1
        mismatch(row, case, False, said)
    elif result == "accepted":
        row.accepted += 1
        mismatch(row, case, True, said)
    else:
        row.crash(f"{case.name}: {said}")


def readers_child() -> None:
    """The child of :func:`readers_row`: paths on stdin (JSON), one JSON line per path
    with the child's resident high-water mark so far (bytes)."""
    baseline = start_peak()
    for path in json.loads(sys.stdin.read()):
        try:
            volume = miss.load_volume(path)
        except MissError as exc:
            result, said = "refused", f"{type(exc).__name__}: {exc}"
        except Exception as exc:  # noqa: BLE001 - counting what should never happen
            result, said = "crash", f"{type(exc).__name__}: {exc}"
        else:
            result, said = "accepted", f"a volume {volume.dims}"
        peak = baseline + peak_since(baseline)
        print(json.dumps({"result": result, "said": said[:500], "peak": peak}), flush=True)


def _miss_info(path: Path) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "miss.cli", "info", str(path)]
    return subprocess.run(
        cmd, capture_output=True, text=True, errors="replace", timeout=300, check=False
    )


def cli_row(cases: list[Any]) -> Row:
    """``miss info`` on every case, two processes at a time."""
    row = Row("CLI (miss info)")
    t0 = time.perf_counter()
    with ThreadPoolExecutor(2) as pool:
        done = list(pool.map(_miss_info, [c.path for c in cases]))
    for case, proc in zip(cases, done, strict=True):
        row.tried += 1
        err = proc.stderr.strip()
        if "Traceback" in err or proc.returncode not in (0, 2):
            row.crash(f"{case.name}: exit {proc.returncode}: {err[-300:]}")
        elif proc.returncode == 2 and len(err.splitlines()) == 1:
            row.refused += 1
            mismatch(row, case, False, err)
        elif proc.returncode == 2:
            row.crash(f"{case.name}: exit 2 with {len(err.splitlines())} lines on stderr")
        else:
            row.accepted += 1
            mismatch(row, case, True, "exit 0")
    row.seconds = time.perf_counter() - t0
    # Run in a child of its own (``in_child``): its largest child is the largest ``miss info``.
    row.peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    return row


# -- a real server -------------------------------------------------------------------------


class Served:
    """``miss serve`` (the load benchmark's), its log, its memory and an admin client."""

    def __init__(self, work: Path) -> None:
        (work / "data").mkdir(parents=True)
        self.data_dir = work / "data"
        self.proc, self.url = start_server(work / "data")
        self.log = work / "server.log"
        self.http = httpx.Client(base_url=self.url, headers=log_in(self.url, "admin"),
                                 timeout=TIMEOUT)  # fmt: skip

    def tracebacks(self) -> int:
        """Unhandled exceptions so far (uvicorn's marker; libraries such as pydicom log
        tracebacks of errors they handle, which are not counted)."""
        return self.log.read_text(errors="replace").count("Exception in ASGI application")

    def reset_peak(self) -> None:
        Path(f"/proc/{self.proc.pid}/clear_refs").write_text("5")

    def peak_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
        return 0.0

    def stop(self) -> None:
        self.http.close()
        self.proc.send_signal(signal.SIGTERM)
        self.proc.wait(timeout=60)


def answer(row: Row, r: httpx.Response, what: str) -> bool:
    """Count one answer; True when it was a 2xx."""
    if r.status_code >= 500:
        row.server_errors += 1
        row.notes.append(f"{what}: {r.status_code} {r.text[:300]}")
        return False
    if r.status_code >= 400:
        try:
            detail = r.json().get("detail")
        except (ValueError, AttributeError):
            detail = None
        if isinstance(detail, str) and detail.strip():
            row.refused += 1
        else:
            row.crash(f"{what}: {r.status_code} without a detail: {r.text[:200]}")
        return False
    row.accepted += 1
    return True


def upload_row(server: Served, cases: list[Any], root: Path, work: Path) -> Row:
    from corpus.upload import as_upload

    row = Row("upload API (POST /api/volumes)")
    zips = work / "zips"
    zips.mkdir()
    server.reset_peak()
    before, t0 = server.tracebacks(), time.perf_counter()
    for case in cases:
        row.tried += 1
        path = as_upload(Path(case.path), root, zips)
        try:
            with open(path, "rb") as f:
                r = server.http.post("/api/volumes", files={"file": (path.name, f)})
        except httpx.HTTPError as exc:
            row.crash(f"{case.name}: {type(exc).__name__}: {exc}")
            continue
        if answer(row, r, case.name):
            server.http.delete(f"/api/volumes/{r.json()['id']}")
        mismatch(row, case, r.status_code < 300, f"{r.status_code} {r.text[:200]}")
    row.seconds = time.perf_counter() - t0
    row.crashes += server.tracebacks() - before
    row.peak_mb = server.peak_mb()
    return row


# -- attack corpus ---------------------------------------------------------------------------


def attack_targets(server: Served, work: Path) -> dict[str, Path]:
    """Files an attacker would want: a secret beside the server, its database, another
    account's stored volume (uploaded here first; /proc paths come with the corpus)."""
    from corpus.attacks import SIDE, mha

    secret = work / "secret.bin"
    secret.write_bytes(np.random.default_rng(1).bytes(4 * SIDE**3))
    other = mha(["ElementDataFile = LOCAL"], ndims=3, local=False)
    other += np.random.default_rng(2).bytes(SIDE**3)
    r = server.http.post("/api/volumes", files={"file": ("other.mha", other)})
    r.raise_for_status()
    data = server.data_dir / "volumes" / r.json()["id"] / "data.zarr" / "c" / "0" / "0" / "0"
    return {"secret": secret, "database": server.data_dir / "miss.sqlite3", "volume": data}


def outside_bytes(voxels: bytes, target: bytes) -> int:
    """Bytes of ``target`` (its first 4096, 32 at a time) found in ``voxels``."""
    windows = (target[i : i + 32] for i in range(0, len(target) - 31, 32))
    return 32 * sum(1 for w in windows if len(set(w)) >= 8 and w in voxels)


def attack_row(server: Served, work: Path) -> Row:
    """``tests/corpus/attacks.py``: uploads that try to make a reader open another file."""
    from corpus.attacks import SIDE, attacks

    row = Row("attack corpus (POST /api/volumes)")
    targets = attack_targets(server, work)
    cases = attacks(targets)
    wanted = {}
    for case in cases:
        path = case.target
        if path.parts[:3] == ("/", "proc", "self"):
            path = Path("/proc", str(server.proc.pid), *path.parts[3:])
        try:
            wanted[case.target] = path.read_bytes()[: SIDE**3]
        except OSError:
            wanted[case.target] = b""
    known = set((server.data_dir / "volumes").iterdir())
    server.reset_peak()
    before, t0 = server.tracebacks(), time.perf_counter()
    for case in cases:
        row.tried += 1
        r = server.http.post("/api/volumes", files={"file": (case.filename, case.content)})
        if answer(row, r, case.name):
            stored = server.data_dir / "volumes" / r.json()["id"] / "data.zarr"
            voxels = np.asarray(chunked.open_array(stored)[0]).tobytes(order="F")
            found = outside_bytes(voxels, wanted[case.target])
            row.outside_bytes += found
            if found:
                row.notes.append(f"{case.name}: {found} bytes of {case.target} stored")
            server.http.delete(f"/api/volumes/{r.json()['id']}")
    row.seconds = time.perf_counter() - t0
    row.crashes += server.tracebacks() - before
    row.peak_mb = server.peak_mb()
    assert set((server.data_dir / "volumes").iterdir()) <= known
    return row


# -- JSON API fuzz ---------------------------------------------------------------------------

EDGES: list[Any] = [0, -1, 1, 0.5, -0.0, 5e-324, 2**31, 2**63, -(2**63) - 1, 10**30, 10**400,
                    1e308, -1e308, float("nan"), float("inf"), float("-inf"), "", "all",
                    "../../etc/passwd", "\x00", "NaN", "1e999", "ﬁ\u202e\U0001f600"]  # fmt: skip
LETTERS = "abcxyz019 _-./\\\"'{}[]:,\x00\x1f\u00e9\u202e\U0001f600"


def fuzz_text(rng: random.Random) -> str:
    return "".join(rng.choice(LETTERS) for _ in range(rng.randint(0, 12)))


def fuzz_value(rng: random.Random, depth: int = 0) -> Any:
    """Arbitrary JSON, NaN and Infinity included (Python's JSON writes them as literals)."""
    pick = rng.random()
    if depth < 3 and pick < 0.12:
        return [fuzz_value(rng, depth + 1) for _ in range(rng.randint(0, 4))]
    if depth < 3 and pick < 0.22:
        return {fuzz_text(rng): fuzz_value(rng, depth + 1) for _ in range(rng.randint(0, 4))}
    return rng.choice([
        None, rng.random() < 0.5, rng.randint(-(10**6), 10**6), rng.choice(EDGES),
        rng.uniform(-1e4, 1e4), fuzz_text(rng),
    ])  # fmt: skip


class Targets:
    """What the fuzz aims at: a small CT-like ball, a label map, a finished model."""

    def __init__(self, server: Served, work: Path) -> None:
        import nibabel as nib

        i, j, k = np.mgrid[:24, :24, :24]
        ball = np.where((i - 12) ** 2 + (j - 12) ** 2 + (k - 12) ** 2 < 64, 1000, -1000)
        labels = np.zeros((16, 16, 16), np.uint8)
        labels[2:7, 2:7, 2:7], labels[9:14, 9:14, 9:14] = 1, 2
        ids = []
        for name, data in (("ball.nii.gz", ball.astype(np.int16)), ("labels.nii.gz", labels)):
            raw = gzip.compress(nib.Nifti1Image(data, np.eye(4)).to_bytes())
            r = server.http.post("/api/volumes", files={"file": (name, raw)})
            ids.append(r.json()["id"])
        self.ball, self.labels = ids
        job = {"level": 0, "sample_rate": 2, "decimate": "none"}
        headers = dict(server.http.headers)
        self.model = wait_done(server.url, headers, submit(server.url, headers, self.ball, job))[
            "id"
        ]
        self.valid = {
            "/api/models": {"volume": self.ball, **job},
            "/api/models#labels": {"volume": self.labels, "labels": [1, 2], "decimate": "none"},
            "/api/shares": {"model": self.model, "expires_in": 3600},
            "/api/auth/login": {"username": "admin", "password": PASSWORD},
            "/api/users": {"name": "fuzzed", "password": "fuzzed-password"},
        }


def fuzz_request(rng: random.Random, t: Targets) -> tuple[str, str, dict[str, Any]]:
    """(method, path, httpx keyword arguments) of one fuzzed request."""
    endpoint = rng.choice(list(t.valid))
    body: Any = dict(t.valid[endpoint])
    path = endpoint.split("#")[0]
    how = rng.random()
    if how < 0.55:
        body[rng.choice([*body, "extra"])] = fuzz_value(rng)
    elif how < 0.65 and body:
        body.pop(rng.choice(list(body)))
    elif how < 0.8:
        body = fuzz_value(rng)
    elif how < 0.88:
        raw = bytes(rng.randrange(256) for _ in range(rng.randint(0, 200)))
        kind = rng.choice(["application/json", "text/plain", "multipart/form-data; boundary=x"])
        return (
            "POST",
            rng.choice([path, "/api/volumes"]),
            {"content": raw, "headers": {"content-type": kind}},
        )
    else:
        return "GET", *_fuzz_query(rng, t)
    raw = json.dumps(body, allow_nan=True).encode()
    return "POST", path, {"content": raw, "headers": {"content-type": "application/json"}}


def _fuzz_query(rng: random.Random, t: Targets) -> tuple[str, dict[str, Any]]:
    def q() -> str:
        return str(rng.choice([rng.choice(EDGES), fuzz_text(rng), rng.uniform(-5e3, 5e3)]))

    if rng.random() < 0.5:
        axis = rng.choice(["axial", "coronal", "sagittal", "oblique"])
        params = {k: q() for k in rng.sample(["window", "level", "threshold", "size"], 2)}
        index = rng.choice([str(rng.randint(-3, 30)), q()])
        from urllib.parse import quote

        return f"/api/volumes/{t.ball}/slices/{axis}/{quote(index, safe='')}.png", {
            "params": params
        }
    return f"/api/models/{t.model}/room/events", {"params": {"session": q()}}


def fuzz_row(server: Served, work: Path, seconds: float, seed: int) -> Row:
    row = Row("JSON API fuzz")
    targets = Targets(server, work)
    rng = random.Random(seed)
    server.reset_peak()
    before, t0 = server.tracebacks(), time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        method, path, kwargs = fuzz_request(rng, targets)
        row.tried += 1
        try:
            r = server.http.request(method, path, **kwargs)
        except httpx.HTTPError as exc:
            row.crash(f"{method} {path}: {type(exc).__name__}: {exc}")
            continue
        answer(row, r, f"{method} {path} {str(kwargs)[:200]}")
    row.seconds = time.perf_counter() - t0
    row.crashes += server.tracebacks() - before
    row.peak_mb = server.peak_mb()
    return row


# -- reader fuzz -----------------------------------------------------------------------------


def reader_fuzz_row(seconds: float, seed: int) -> Row:
    """``fuzz_readers`` of ``tests/corpus/fuzz.py`` (its workers' peak: run it in a child)."""
    row = Row("reader fuzz (mutated files)")
    try:
        from corpus.fuzz import fuzz_readers
    except ImportError:
        row.notes.append("skipped: tests/corpus/fuzz.py (fuzz_readers) is not there yet")
        return row
    t0 = time.perf_counter()
    found = fuzz_readers(seconds, seed)
    row.seconds = time.perf_counter() - t0
    row.peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    row.tried, row.refused = int(found["cases"]), int(found["refused"])
    row.accepted = int(found["loaded"])
    row.crashes = sum(found["crashes"].values())
    row.notes += [f"{kind}: {json.dumps(ex)[:300]}" for kind, ex in found["examples"].items()]
    return row


def in_child(name: str, payload: Any) -> Row:
    """A row computed by this script in a fresh process (``--row NAME``), so that the
    largest of *its* children is that row's peak."""
    proc = subprocess.run(
        [sys.executable, __file__, "--row", name], input=json.dumps(payload), text=True,
        capture_output=True, errors="replace", check=False,
    )  # fmt: skip
    if proc.returncode != 0 or not proc.stdout.strip():
        row = Row(name)
        row.crash(f"the {name} row died ({proc.returncode}): {proc.stderr[-600:]}")
        return row
    return Row(**json.loads(proc.stdout.strip().splitlines()[-1]))


def row_child(name: str) -> None:
    """``--row NAME``: payload on stdin, the row as one JSON line on stdout."""
    payload = json.loads(sys.stdin.read())
    if name == "cli":
        cases = [SimpleNamespace(**c) for c in payload]
        row = cli_row(cases)
    else:
        row = reader_fuzz_row(payload["seconds"], payload["seed"])
    print(json.dumps(asdict(row)))


# -- the run ---------------------------------------------------------------------------------


def run(seconds: float, seed: int) -> list[Row]:
    with tempfile.TemporaryDirectory(prefix="miss-robustness-") as tmp:
        work = Path(tmp)
        root = work / "corpus"
        cases = corpus(root)
        print(f"corpus: {len(cases)} cases", file=sys.stderr, flush=True)
        plain = [{"name": c.name, "path": str(c.path), "expect": c.expect} for c in cases]
        rows = [readers_row(cases), in_child("cli", plain)]
        print("readers and CLI done; starting miss serve", file=sys.stderr, flush=True)
        server = Served(work / "server")
        try:
            rows.append(upload_row(server, cases, root, work))
            rows.append(attack_row(server, work))
            rows.append(fuzz_row(server, work, seconds, seed))
        except Exception:  # noqa: BLE001 - report what the run reached
            traceback.print_exc()
            raise
        finally:
            server.stop()
        rows.append(in_child("reader fuzz", {"seconds": seconds, "seed": seed}))
    return rows


def main(argv: list[str] | None = None) -> int:
    if argv is None and sys.argv[1:] == ["--readers-child"]:
        readers_child()
        return 0
    if argv is None and sys.argv[1:2] == ["--row"]:
        row_child(sys.argv[2])
        return 0
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seconds", type=float, default=30.0, help="per fuzz row")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args(argv)
    rows = run(args.seconds, args.seed)
    table = markdown_table(HEADER, [r.cells() for r in rows])
    notes = [f"- {r.surface}: {n}" for r in rows for n in r.notes[:12]]
    text = (
        f"Robustness (fuzz {args.seconds:g} s per row, seed {args.seed}); 5xx and crashes "
        "must be 0.\n\n" + table + ("\nNotes:\n\n" + "\n".join(notes) + "\n" if notes else "")
    )
    print(text)
    save("robustness", {"seconds": args.seconds, "seed": args.seed,
                        "rows": [asdict(r) for r in rows]}, text)  # fmt: skip
    return 1 if any(r.server_errors or r.crashes or r.outside_bytes for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
