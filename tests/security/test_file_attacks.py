"""Attacks through uploaded files, against a real ``miss serve``: headers that name other
files (the server's database, its environment, another user's volume, any file), zip
bombs in pieces, too many uploads at once, a disk filled mid-upload, secrets on a
worker's command line; and the confinement itself, below every parser."""

from __future__ import annotations

import io
import os
import secrets
import shutil
import subprocess
import sys
import threading
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import landlockpy
import numpy as np
import pytest
from support import ADMIN_PASSWORD
from support.realserver import Server, serving

from miss.errors import UnreadableVolume, UnsupportedFormat
from miss.io import confined
from miss.server.storage import chunked

MB = 1 << 20
#: The tests of the confinement itself need a kernel with Landlock (the server without it
#: is tested too: it refuses the formats that name other files).
needs_landlock = pytest.mark.skipif(
    landlockpy.abi_version() < 1,
    reason="this kernel has no Landlock (Linux 5.13+ with Landlock in its LSM list)",
)
SIDE = 16  # a 16^3 volume of bytes: 4096 voxels, each one byte of whatever was read


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    folder = tmp_path_factory.mktemp("attacks")
    with serving(folder / "data", folder / "server.log") as running:
        yield running


@pytest.fixture(scope="module")
def secret(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A file outside the data folder whose bytes must never come back as voxels."""
    path = tmp_path_factory.mktemp("outside") / "secret.bin"
    path.write_bytes(secrets.token_bytes(4 * SIDE**3))
    return path


def mha(data_field: str, *, decoy: bool = True, newline: str = "\n", ndims: int = 3) -> bytes:
    """A MetaImage header whose first data-file line is ``data_field``; with ``decoy`` a
    second ``ElementDataFile = LOCAL`` follows, and LOCAL voxels after it (a ramp).
    ``ndims=4`` (a fourth axis of 1) is a variant MISS leaves to SimpleITK."""
    sizes = " ".join([str(SIDE)] * 3 + ["1"] * (ndims - 3))
    lines = ["ObjectType = Image", f"NDims = {ndims}", f"DimSize = {sizes}"]
    lines += ["ElementType = MET_UCHAR", data_field]
    if decoy:
        lines.append("ElementDataFile = LOCAL")
    ramp = (np.arange(SIDE**3) % 251).astype(np.uint8).tobytes()
    return newline.join(lines).encode() + newline.encode() + ramp


def volume_dirs(server: Server) -> set[Path]:
    return set((server.data_dir / "volumes").iterdir())


def leaked(new: set[Path], needle: bytes) -> bool:
    """A volume stored by the attack holds ``needle`` (bytes from outside the upload)."""
    return any(needle in voxel_bytes(folder) for folder in new)


def distinctive(path: Path) -> bytes:
    """32 bytes from the start of ``path`` (what a 16^3 byte volume would hold) that no
    ramp or constant could match by chance."""
    data = path.read_bytes()[: SIDE**3]
    return next(
        data[i : i + 32] for i in range(0, len(data) - 32, 8) if len(set(data[i : i + 32])) >= 8
    )


def targets(server: Server, secret: Path) -> dict[str, Path]:
    volumes = server.http.get("/api/volumes").json()
    demo_id = next(v["id"] for v in volumes if v["name"].startswith("Demo head phantom"))
    demo = server.data_dir / "volumes" / demo_id / "data.zarr" / "c" / "0" / "0" / "0"
    return {
        "file": secret,
        "database": server.data_dir / "miss.sqlite3",
        "environment": Path("/proc/self/environ"),
        "other volume": demo,
    }


FORMS = {
    "colon": "ElementDataFile: {}",
    "colon, no blank": "ElementDataFile:{}",
    "blanks and tab": "   ElementDataFile \t:  {}",
    "colon equals": "ElementDataFile := {}",
    "lower case": "elementdatafile = {}",
    "spaced name": "Element Data File = {}",
    "dot dot": "ElementDataFile: ../../../../../../../../..{}",
}


def voxel_bytes(folder: Path) -> bytes:
    """A stored volume's voxels as bytes, Fortran order (as the volume's source hash)."""
    return np.asarray(chunked.open_array(folder / "data.zarr")[0][:]).tobytes(order="F")


@pytest.mark.parametrize("form", list(FORMS))
@pytest.mark.parametrize("target", ["file", "database", "environment", "other volume"])
def test_a_header_cannot_make_the_server_read_another_file(
    server: Server, secret: Path, form: str, target: str
) -> None:
    """The finding: ``ElementDataFile: /path`` before a decoy ``= LOCAL`` passed MISS's
    check (``=`` lines only) and SimpleITK followed it; slices then served the bytes."""
    path = targets(server, secret)[target]
    needle = b"MISS_ADMIN_PASSWORD" if target == "environment" else distinctive(path)
    before = volume_dirs(server)
    answers = []
    for newline, ndims in (("\n", 3), ("\r\n", 3), ("\n", 4), ("\r\n", 4)):
        body = mha(FORMS[form].format(path), newline=newline, ndims=ndims)
        answers.append(server.http.post("/api/volumes", files={"file": ("head.mha", body)}))
    assert not leaked(volume_dirs(server) - before, needle), f"{target} leaked via {form}"
    for r in answers:  # and refused outright: which line a reader takes is no guess to make
        assert 400 <= r.status_code < 500 and "detail" in r.json(), (form, r.text[:300])
    assert volume_dirs(server) == before


def test_a_header_with_two_data_files_is_refused(server: Server, tmp_path: Path) -> None:
    """Even when both names are inside the upload: which one a reader takes is not MISS's
    guess to make."""
    body = mha("ElementDataFile = LOCAL", decoy=False)
    twice = body.replace(
        b"ElementDataFile = LOCAL", b"ElementDataFile: a.raw\nElementDataFile = LOCAL"
    )
    r = server.http.post("/api/volumes", files={"file": ("twice.mha", twice)})
    assert r.status_code == 422 and "twice" in r.json()["detail"], r.text
    r = server.http.post("/api/volumes", files={"file": ("once.mha", body)})
    assert r.status_code == 201, r.text


@pytest.mark.parametrize(
    "field",
    [
        "data file: {}",
        "DATA FILE: {}",
        "datafile: {}",
        "data file: LIST\n{}",
        "data file: ../../../../../../../..{}",
    ],
)
def test_nrrd_data_file_fields_cannot_leave_the_upload(
    server: Server, secret: Path, field: str
) -> None:
    header = (
        "NRRD0004\ntype: uchar\ndimension: 3\n"
        f"sizes: {SIDE} {SIDE} {SIDE}\nencoding: raw\n" + field.format(secret) + "\n\n"
    ).encode()
    zipped = io.BytesIO()
    with zipfile.ZipFile(zipped, "w") as zf:
        zf.writestr("head.nhdr", header)
    before = volume_dirs(server)
    r = server.http.post("/api/volumes", files={"file": ("head.zip", zipped.getvalue())})
    assert 400 <= r.status_code < 500, r.text
    assert volume_dirs(server) == before


@needs_landlock
def test_the_confined_reader_cannot_open_what_a_header_names(secret: Path, tmp_path: Path) -> None:
    """Below every parser: a data file that passes every name check (a link inside the
    upload's folder, as no upload can make) still cannot be opened outside that folder."""
    data = tmp_path / "data"
    work = data / "tmp" / "upload"
    work.mkdir(parents=True)
    (work / "head.mhd").write_bytes(mha("ElementDataFile = voxels.raw", decoy=False)[: -(SIDE**3)])
    (work / "voxels.raw").symlink_to(secret)
    found = confined.probe(data)
    assert found.confined, found.problem
    if landlockpy.abi_version() >= 4:  # the probe's child tried to connect over TCP too
        assert found.mechanism.endswith("no TCP"), found.mechanism
    limits = confined.Limits(seconds=60, memory_bytes=2 << 30)
    with pytest.raises(UnreadableVolume) as refused:
        confined.parse_upload(work, "head.mhd", found, limits)
    assert secret.read_bytes()[:8].hex() not in str(refused.value)
    # Unconfined (no Landlock here), a header that names another file is not even tried.
    with pytest.raises(UnsupportedFormat, match="cannot confine"):
        confined.parse_upload(work, "head.mhd", confined.Confinement(problem="test"), limits)


@needs_landlock
def test_the_probe_refuses_a_data_folder_inside_what_readers_may_read(tmp_path: Path) -> None:
    inside = Path(sys.prefix) / f"miss-test-{os.getpid()}"
    try:
        found = confined.probe(inside)
        assert not found.confined and "lies inside" in found.problem, found
    finally:
        shutil.rmtree(inside, ignore_errors=True)
    assert confined.probe(tmp_path / "data").confined
    # A server started as a script (or with -m) from the folder that holds its data folder
    # has that folder on sys.path; the child does not need it, so it is no reason to refuse.
    script = tmp_path / "start.py"
    script.write_text(
        "import sys\nfrom pathlib import Path\nfrom miss.io import confined\n"
        "found = confined.probe(Path(sys.argv[1]))\nprint(found.confined, found.problem)\n"
    )
    said = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "data")], capture_output=True, text=True
    )
    assert said.stdout.startswith("True"), said.stdout + said.stderr


def bomb(members: int, size: int) -> bytes:
    out = io.BytesIO()
    zeros = bytes(size)
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED, compresslevel=9) as zf:
        for n in range(members):
            zf.writestr(f"series/slice{n:04d}.dcm", zeros)
    return out.getvalue()


def test_a_zip_bomb_in_pieces_is_refused_before_it_is_unpacked(server: Server) -> None:
    """The finding: members just under the per-member floor (64 MiB) passed the ratio
    check, so a few hundred kB of zip wrote hundreds of MB (gigabytes with more)."""
    body = bomb(6, 60 * MB)  # 360 MB of zeros in about 350 kB
    assert len(body) < MB
    r = server.http.post("/api/volumes", files={"file": ("series.zip", body)})
    assert r.status_code == 422, r.text
    assert "zip bomb" in r.json()["detail"] and "the zip would inflate" in r.json()["detail"]
    assert list((server.data_dir / "tmp").iterdir()) == []


def multipart(chunks: Iterator[bytes], filename: str) -> tuple[Iterator[bytes], dict[str, str]]:
    boundary = "miss-attack-boundary"
    head = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="file"; filename="{filename}"\r\n'
        "Content-Type: application/octet-stream\r\n\r\n"
    ).encode()

    def body() -> Iterator[bytes]:
        yield head
        yield from chunks
        yield f"\r\n--{boundary}--\r\n".encode()

    return body(), {"Content-Type": f"multipart/form-data; boundary={boundary}"}


def slow(seconds: float) -> Iterator[bytes]:
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        yield b"\0" * 4096
        time.sleep(0.05)


def start_slow_upload(url: str, token: str, seconds: float) -> threading.Thread:
    def send() -> None:
        body, headers = multipart(slow(seconds), "slow.nii")
        with httpx.Client(base_url=url, timeout=60) as http:
            http.post("/api/volumes", content=body, headers=headers | bearer(token))

    thread = threading.Thread(target=send, daemon=True)
    thread.start()
    return thread


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def add_user(server: Server, name: str) -> str:
    """A new account; its bearer token (logged in by a client of its own)."""
    password = f"{name}-password-1"
    r = server.http.post("/api/users", json={"name": name, "password": password})
    assert r.status_code == 201, r.text
    with httpx.Client(base_url=server.url) as http:
        r = http.post("/api/auth/login", json={"username": name, "password": password})
    return r.json()["token"]


def test_uploads_at_once_are_limited_per_account_and_in_all(tmp_path: Path) -> None:
    """Each upload holds disk, a reader process and memory until it is stored: a client
    may not start more than its share at once (429 with Retry-After, nothing kept)."""
    env = {"MISS_UPLOADS_PER_USER": "1", "MISS_UPLOADS_AT_ONCE": "2", "MISS_DEMO": "0"}
    with serving(tmp_path / "data", tmp_path / "server.log", env=env) as server:
        ana, bob = add_user(server, "ana"), add_user(server, "bob")
        first = start_slow_upload(server.url, server.token, 5)
        second = start_slow_upload(server.url, ana, 5)
        time.sleep(1.5)
        junk = {"file": ("b.nii", b"x" * 1000)}
        r = server.http.post("/api/volumes", files=junk)
        assert r.status_code == 429 and int(r.headers["Retry-After"]) >= 1, r.text
        assert "this account" in r.json()["detail"], r.text
        r = server.http.post("/api/volumes", files=junk, headers=bearer(bob))
        assert r.status_code == 429 and "at most 2 at once" in r.json()["detail"], r.text
        first.join(60)
        second.join(60)
        r = server.http.post("/api/volumes", files=junk, headers=bearer(bob))
        assert r.status_code in (415, 422), r.text  # a slot again: read, and refused as junk
        assert server.http.get("/api/volumes").json() == []


def tmpfs_wrap(mountpoint: Path, size_mb: int) -> list[str]:
    """Run the command in a mount namespace with a ``size_mb`` tmpfs at ``mountpoint``."""
    script = f'mount -t tmpfs -o size={size_mb}m miss-test "$0" && exec "$@"'
    return ["unshare", "--mount", "sh", "-c", script, str(mountpoint)]


def test_the_disk_is_watched_while_an_upload_arrives(tmp_path: Path) -> None:
    """Free space was checked only before an upload: one that filled the disk past the
    minimum was written to the end. Now it stops at the minimum with 507, nothing kept."""
    probe = subprocess.run([*tmpfs_wrap(tmp_path, 1), "true"], capture_output=True, timeout=30)
    if probe.returncode != 0:
        pytest.skip(f"mounting a tmpfs (unshare --mount) failed here: {probe.stderr!r}")
    data = tmp_path / "data"
    data.mkdir()
    env = {"MISS_DEMO": "0", "MISS_MIN_FREE_MB": "40"}
    with serving(data, tmp_path / "server.log", env=env, wrap=tmpfs_wrap(data, 64)) as server:
        inside = server.path(data)
        body, headers = multipart((bytes(MB) for _ in range(45)), "big.nii")
        r = server.http.post("/api/volumes", content=body, headers=headers)
        assert r.status_code == 507 and r.json()["detail"].startswith("disk full"), r.text
        assert [p for p in (inside / "tmp").rglob("*") if p.is_file()] == []


def worker_processes() -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if b"miss.server.jobs.worker" in (entry / "cmdline").read_bytes():
                    found.append(int(entry.name))
            except OSError:
                continue
    return found


def test_a_worker_shows_no_database_url_and_has_no_admin_password(server: Server) -> None:
    """The database URL (with its password, on PostgreSQL) was on the worker's command
    line, which every local user can read; the admin password was in its environment."""
    demo = server.http.get("/api/volumes").json()[-1]["id"]  # the demo: the oldest, listed last
    job = server.submit(demo, level=250, sample_rate=1, decimate="schroeder")
    seen: list[int] = []
    deadline = time.monotonic() + 60
    while not seen and time.monotonic() < deadline:
        seen = worker_processes()
        time.sleep(0.01)
    assert seen, "no worker process seen"
    for pid in seen:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        assert (
            b"sqlite:" not in cmdline
            and str(server.data_dir / "miss.sqlite3").encode() not in cmdline
        )
        environ = Path(f"/proc/{pid}/environ").read_bytes()
        assert b"MISS_ADMIN_PASSWORD" not in environ and ADMIN_PASSWORD.encode() not in environ
    assert server.wait(job, ("done", "failed"))["status"] == "done"


def test_without_confinement_the_server_says_so_and_refuses_pointing_formats(
    tmp_path: Path, small_nifti: bytes
) -> None:
    """Where Landlock cannot confine the readers (here: a data folder inside the Python
    installation, which the readers must read), one line at start says so, and headers
    that name other files are refused; self-contained formats still work."""
    data = Path(sys.prefix) / f"miss-test-data-{os.getpid()}"
    log = tmp_path / "server.log"
    try:
        with serving(data, log, env={"MISS_DEMO": "0"}) as server:
            said = [ln for ln in log.read_text().splitlines() if "NOT confined" in ln]
            assert len(said) == 1 and "lies inside" in said[0], log.read_text()
            body = mha("ElementDataFile = LOCAL", decoy=False)
            r = server.http.post("/api/volumes", files={"file": ("ok.mha", body)})
            assert r.status_code == 201, r.text
            detached = io.BytesIO()
            with zipfile.ZipFile(detached, "w") as zf:
                zf.writestr("head.mhd", body[: -(SIDE**3)].replace(b"LOCAL", b"head.raw"))
                zf.writestr("head.raw", body[-(SIDE**3) :])
            r = server.http.post("/api/volumes", files={"file": ("h.zip", detached.getvalue())})
            assert r.status_code == 415 and "cannot confine" in r.json()["detail"], r.text
            r = server.http.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)})
            assert r.status_code == 201, r.text
    finally:
        shutil.rmtree(data, ignore_errors=True)
