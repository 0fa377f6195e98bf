"""Volumes stored as chunked Zarr (``miss.server.storage.chunked``): round trips, the
metadata check, a full disk, and the figures gathered plane by plane against the old
whole-array ones."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from miss.errors import DiskFull, UnreadableVolume
from miss.server.storage import chunked
from miss.server.volumes import imaging
from miss.server.volumes.summary import Summary
from miss.surface.blocks import ChunkCache

AFFINE = np.array([[-0.8, 0, 0, 100.5], [0, -0.7, 0.1, -20], [0, 0, 2.5, 33], [0, 0, 0, 1]])


def old_source_hash(data: np.ndarray, affine: np.ndarray) -> str:
    """``source_sha256`` as MISS computed it before Zarr: of the whole array at once."""
    digest = hashlib.sha256(np.ascontiguousarray(np.asfortranarray(data).T).data)
    digest.update(np.ascontiguousarray(affine, dtype="<f8").data)
    return digest.hexdigest()


@pytest.mark.parametrize(
    ("dtype", "shape"),
    [("int16", (130, 70, 150)), ("uint8", (5, 64, 65)), ("float32", (64, 2, 3))],
)
def test_round_trip_voxels_and_affine(tmp_path: Path, dtype: str, shape: tuple) -> None:
    rng = np.random.default_rng(1)
    data = np.asfortranarray(rng.integers(0, 200, shape).astype(dtype))
    path = tmp_path / "data.zarr"
    chunked.write_array(path, data, {"affine": AFFINE, "provenance": {"source_sha256": "x"}})
    array, affine, attributes = chunked.open_array(path)
    assert np.array_equal(array[:], data) and array.dtype == data.dtype
    assert np.array_equal(affine, AFFINE)
    assert attributes["provenance"] == {"source_sha256": "x"}
    whole = chunked.read(path, in_memory_max=data.nbytes)
    assert isinstance(whole, np.ndarray) and whole.flags.f_contiguous
    assert not whole.flags.writeable and np.array_equal(whole, data)
    lazy = chunked.read(path, in_memory_max=data.nbytes - 1)
    assert not isinstance(lazy, np.ndarray) and np.array_equal(lazy[:, 1, :], data[:, 1, :])
    assert np.array_equal(lazy[3, ..., ::2], data[3, ..., ::2])
    assert np.array_equal(lazy[1:-2:3, 1], data[1:-2:3, 1])
    assert (lazy.min(), lazy.max()) == (data.min(), data.max())
    assert np.array_equal(np.asarray(lazy), data)
    assert chunked.nbytes(path) == data.nbytes
    assert [p.name for p in tmp_path.iterdir()] == ["data.zarr"]  # no staging folder left


@pytest.mark.parametrize(
    ("dtype", "shape"), [("int16", (130, 70, 150)), ("uint8", (5, 64, 65)), ("float64", (3, 2, 70))]
)
def test_a_chunk_read_from_its_file_is_zarrs_chunk(
    tmp_path: Path, dtype: str, shape: tuple
) -> None:
    rng = np.random.default_rng(2)
    data = np.asfortranarray(rng.integers(1, 200, shape).astype(dtype))
    data[:64, :64, :64] = 0  # a chunk of the fill value: zarr writes no file for it
    path = tmp_path / "data.zarr"
    chunked.write_array(path, data, {"affine": AFFINE})
    array = chunked.open_array(path)[0]
    assert not (path / "c" / "0" / "0" / "0").exists()
    counts = [-(-n // c) for n, c in zip(shape, array.chunks, strict=True)]
    for index in np.ndindex(*counts):
        box = tuple(slice(i * c, (i + 1) * c) for i, c in zip(index, array.chunks, strict=True))
        got = array.chunk(index)
        assert got.shape == array.chunks and got.dtype == data.dtype  # edge chunks whole
        part = data[box]
        assert np.array_equal(got[tuple(slice(0, n) for n in part.shape)], part)


@settings(max_examples=60, deadline=None)
@given(st.data())
def test_reads_from_the_chunk_files_equal_zarrs(tmp_path_factory, data) -> None:
    """Any basic index (integers, negative ones, slices with steps, empty, past the end)
    reads what zarr reads, shape and values."""
    path = _random_store(tmp_path_factory)
    array = chunked.open_array(path)[0]
    key = tuple(data.draw(_index(n)) for n in array.shape)
    want = np.asarray(array.stored[key[::-1]]).T
    got = array[key]
    assert got.shape == want.shape and np.array_equal(got, want)


@settings(max_examples=40, deadline=None)
@given(data=st.data())
def test_reads_through_a_chunk_cache_equal_reads_without(tmp_path_factory, data) -> None:
    """A server's reads through its cache of decompressed chunks (a small one, so that
    chunks come and go) answer what reads from the files answer."""
    path = _random_store(tmp_path_factory)
    cache = _CACHES.setdefault("small", ChunkCache(3 * 64**3 * 2))
    plain, kept = chunked.open_array(path)[0], chunked.open_array(path, cache)[0]
    for _ in range(3):
        key = tuple(data.draw(_index(n)) for n in plain.shape)
        want, got = plain[key], kept[key]
        assert got.shape == want.shape and np.array_equal(got, want)
    assert cache.held <= cache.limit


_CACHES: dict[str, ChunkCache] = {}


def test_kept_chunks_are_read_from_memory(tmp_path: Path) -> None:
    """A cache with room for three of a slice's four chunks keeps three; the second read
    of them opens no chunk file (the files are gone: it still answers the stored
    voxels), and what it answers is read-only."""
    data = np.asfortranarray(np.arange(128 * 128 * 64, dtype=np.int16).reshape(128, 128, 64))
    path = tmp_path / "data.zarr"
    chunked.write_array(path, data, {"affine": AFFINE})
    cache = ChunkCache(3 * 64**3 * 2)  # three of its four chunks
    array = chunked.open_array(path, cache)[0]
    assert np.array_equal(array[:, :, 5], data[:, :, 5])  # four chunks read, three kept
    assert len(cache.chunks) == 3 and cache.held == 3 * 64**3 * 2
    shutil.rmtree(path / "c")
    kept = list(cache.chunks)
    again = chunked.open_array(path, cache)[0]
    for (key,) in kept:  # each kept chunk is answered from memory, read-only
        index = tuple(int(p) for p in Path(key).relative_to(path / "c").parts[::-1])
        chunk = again.chunk(index)
        assert not chunk.flags.writeable
        box = tuple(slice(i * 64, (i + 1) * 64) for i in index)
        assert np.array_equal(chunk, data[box])


def test_deleting_a_volume_forgets_its_kept_chunks(
    make_client: Any, small_nifti: bytes, upload_for: Any
) -> None:
    """A server keeps the chunks its slices read; deleting the volume drops them (the
    other volumes' stay)."""
    client = make_client()
    headers = dict(client.headers)
    ids = [upload_for(client, headers, small_nifti, f"ball{n}.nii.gz")["id"] for n in range(2)]
    for volume_id in ids:
        assert client.get(f"/api/volumes/{volume_id}/slices/axial/3.png").status_code == 200
    store = client.app.state.store
    assert store.chunks is not None

    def held(volume_id: str) -> int:
        return sum(volume_id in key[0] for key in store.chunks.chunks)

    assert held(ids[0]) > 0 and held(ids[1]) > 0
    assert client.delete(f"/api/volumes/{ids[0]}").status_code in (200, 204)
    assert held(ids[0]) == 0 and held(ids[1]) > 0


def test_a_strided_read_holds_the_answer_not_the_box(tmp_path: Path) -> None:
    """Every 16th voxel of a stored 256³ volume (a preview's read): the chunks are read one
    at a time into the answer, never the 32 MB box they span."""
    import tracemalloc

    data = np.asfortranarray(np.arange(256**3, dtype=np.int16).reshape((256,) * 3))
    chunked.write_array(tmp_path / "data.zarr", data, {"affine": AFFINE})
    array = chunked.open_array(tmp_path / "data.zarr")[0]
    del data
    tracemalloc.start()
    try:
        got = array[::16, 3::16, ::16]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    want = np.arange(256**3, dtype=np.int16).reshape((256,) * 3)[::16, 3::16, ::16]
    assert np.array_equal(got, want)
    assert peak < 8 << 20, f"{peak / 2**20:.1f} MB for a {got.nbytes} byte answer"


_STORES: dict[str, Path] = {}


def _random_store(factory) -> Path:
    """One stored (70, 130, 66) int16 volume (chunks of 64: edge chunks on every axis,
    one chunk of the fill value, so no file), made once."""
    if "path" not in _STORES:
        rng = np.random.default_rng(3)
        data = np.asfortranarray(rng.integers(1, 3000, (70, 130, 66)).astype(np.int16))
        data[:64, 64:128, :64] = 0
        path = factory.mktemp("store") / "data.zarr"
        chunked.write_array(path, data, {"affine": AFFINE})
        _STORES["path"] = path
    return _STORES["path"]


def _index(n: int):
    ints = st.integers(-n, n - 1)
    ends = st.one_of(st.none(), st.integers(-n - 3, n + 3))
    slices = st.builds(
        slice, ends, ends, st.one_of(st.none(), st.integers(1, 9), st.integers(60, 140))
    )
    return st.one_of(ints, slices)


def test_a_damaged_chunk_file_is_refused_before_decompressing(tmp_path: Path) -> None:
    path = tmp_path / "data.zarr"
    data = np.ones((70, 3, 3), np.int16, order="F")
    chunked.write_array(path, data, {"affine": AFFINE})
    array = chunked.open_array(path)[0]
    where = path / "c" / "0" / "0" / "1"
    raw = bytearray(where.read_bytes())
    raw[4:8] = (1 << 31).to_bytes(4, "little")  # claims 2 GB once decompressed
    where.write_bytes(bytes(raw))
    with pytest.raises(UnreadableVolume, match="not a Blosc chunk"):
        array.chunk((1, 0, 0))
    where.write_bytes(b"short")
    with pytest.raises(UnreadableVolume, match="restore the data folder"):
        array.chunk((1, 0, 0))


def tampered(meta: dict, change: str) -> dict:
    if change == "gzip codec":
        meta["codecs"][1] = {"name": "gzip", "configuration": {"level": 5}}
    elif change == "big-endian":
        meta["codecs"][0]["configuration"]["endian"] = "big"
    elif change == "object dtype":
        meta["data_type"] = "string"
    elif change == "4-D":
        meta["shape"] = [*meta["shape"], 2]
    elif change == "no affine":
        del meta["attributes"]["affine"]
    elif change == "x, y, z axes":
        meta["dimension_names"] = ["x", "y", "z"]
    elif change == "sharding":
        meta["codecs"].insert(0, {"name": "sharding_indexed", "configuration": {}})
    return meta


@pytest.mark.parametrize(
    "change",
    ["gzip codec", "big-endian", "object dtype", "4-D", "no affine", "x, y, z axes", "sharding"],
)
def test_open_refuses_metadata_miss_does_not_write(tmp_path: Path, change: str) -> None:
    path = tmp_path / "data.zarr"
    chunked.write_array(path, np.zeros((4, 4, 4), np.int16, order="F"), {"affine": AFFINE})
    meta = json.loads((path / "zarr.json").read_text())
    (path / "zarr.json").write_text(json.dumps(tampered(meta, change)))
    with pytest.raises(UnreadableVolume, match="restore the data folder from a MISS backup"):
        chunked.open_array(path)


def test_planes_that_do_not_fit_are_refused_and_leave_nothing(tmp_path: Path) -> None:
    planes = [np.zeros((4, 5), np.int16)] * 3
    with pytest.raises(ValueError, match="got 3 planes for a volume of 4 slices"):
        chunked.write_planes(tmp_path / "a.zarr", (4, 5, 4), "int16", planes, {"affine": AFFINE})
    with pytest.raises(ValueError, match="does not fit"):
        chunked.write_planes(tmp_path / "b.zarr", (5, 4, 3), "int16", planes, {"affine": AFFINE})
    assert list(tmp_path.iterdir()) == []


FILL_TMPFS = """
import json, os, sys
import numpy as np
from pathlib import Path
from miss.errors import DiskFull
from miss.server.storage import chunked
where = Path(sys.argv[1])
noise = np.random.default_rng(0).integers(-30000, 30000, (256, 256, 128)).astype(np.int16)
try:
    chunked.write_array(where / "data.zarr", np.asfortranarray(noise), {"affine": np.eye(4)})
    said = "written"
except DiskFull as exc:
    said = str(exc)
print(json.dumps({"said": said, "left": sorted(p.name for p in where.iterdir())}))
"""


def test_disk_full_on_a_real_small_disk_raises_disk_full_and_leaves_nothing(
    tmp_path: Path,
) -> None:
    """16 MB of noise (incompressible) into an 8 MB tmpfs: ENOSPC mid-write."""
    script = 'mount -t tmpfs -o size=8m miss-test "$0" && exec "$@"'
    wrap = ["unshare", "--mount", "sh", "-c", script, str(tmp_path)]
    probe = subprocess.run([*wrap, "true"], capture_output=True, text=True, timeout=30)
    if probe.returncode != 0:
        pytest.skip(f"needs a tmpfs in a mount namespace (root): {probe.stderr.strip()}")
    run = subprocess.run(
        [*wrap, sys.executable, "-c", FILL_TMPFS, str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    assert out["said"].startswith("disk full:"), out
    assert out["left"] == [], out


def test_disk_full_error_maps_enospc_only(tmp_path: Path, monkeypatch) -> None:
    import errno

    import zarr.storage._local as local

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(local, "_put", full)
    with pytest.raises(DiskFull, match="nothing of them was kept"):
        chunked.write_array(tmp_path / "d.zarr", np.ones((3, 3, 3), np.uint8), {"affine": AFFINE})
    assert list(tmp_path.iterdir()) == []


def test_summary_matches_the_whole_array_figures() -> None:
    """Hash, range, histogram and thumbnail gathered plane by plane equal the old
    whole-array computations (a volume big enough for the histogram to sample slices)."""
    rng = np.random.default_rng(3)
    data = np.asfortranarray(rng.normal(0, 300, (300, 290, 420)).astype(np.float32))
    summary = Summary(data.shape, data.dtype, AFFINE)
    for _ in summary.watch(data[:, :, k] for k in range(data.shape[2])):
        pass
    assert imaging.sample_step(data.shape) > 1
    assert summary.source_sha256 == old_source_hash(data, AFFINE)
    assert (summary.lo, summary.hi) == (float(data.min()), float(data.max()))
    assert summary.histogram() == imaging.histogram(data)
    window = imaging.default_window(summary.histogram())
    assert summary.thumbnail(window) == imaging.thumbnail(data, AFFINE, window)


def test_source_hash_of_a_real_scan_is_unchanged(datasets: Path, tmp_path: Path) -> None:
    """The stored source_sha256 of a real DICOM series and a real NIfTI (streamed) is the
    one the whole-array hash gives."""
    from miss.io import load_volume
    from miss.server.storage.store import Store
    from miss.server.volumes.ingest import ingest_path

    store = Store(tmp_path / "data", f"sqlite:///{tmp_path / 'data' / 'miss.sqlite3'}")
    store.init()
    try:
        for path in (
            datasets / "ct_head_dicom_ge_gantrytilt",
            datasets / "nifti" / "CT_pitch.nii.gz",
        ):
            whole = load_volume(path)
            row = ingest_path(store, path)
            assert row.info["source_sha256"] == old_source_hash(whole.data, whole.affine)
            stored = store.open_volume(row.id)
            assert np.array_equal(stored.data, whole.data)
    finally:
        store.close()


def test_streamed_nifti_is_stored_as_a_whole_read_stores_it(tmp_path: Path) -> None:
    """A big-endian CT-like NIfTI, read plane by plane, gives the files an upload gives:
    same voxels, meta.json (CT detected from the streamed range), histogram, thumbnail."""
    import nibabel as nib

    from miss.deid import deidentify
    from miss.io import load_volume
    from miss.server.storage.store import Store
    from miss.server.volumes.ingest import UID_KEY, ingest_path, stage

    i, j, k = np.indices((60, 50, 70))
    ct = np.where((i - 30) ** 2 + (j - 25) ** 2 + (k - 35) ** 2 < 400, 1200, -1000)
    image = nib.Nifti1Image(ct.astype(">i2"), np.diag([0.9, 0.8, 2.0, 1.0]))
    image.header.set_sform(image.affine, code=1)
    path = tmp_path / "ball.nii.gz"
    nib.save(image, path)
    store = Store(tmp_path / "data", f"sqlite:///{tmp_path / 'data' / 'miss.sqlite3'}")
    store.init()
    try:
        from miss.io.nifti import stream

        assert stream(path) is not None, "the test file should be a plain (streamable) NIfTI"
        row = ingest_path(store, path)
        clean = deidentify(load_volume(path), store.secret(UID_KEY))  # as an upload is
        staged, info = stage(store, clean.volume, clean.report)
        streamed = store.volume_dir(row.id)
        for name in ("histogram.json", "thumbnail.png"):
            assert (streamed / name).read_bytes() == (staged / name).read_bytes(), name
        assert row.info == info and info["modality"] == "CT"
        assert np.array_equal(store.open_volume(row.id).data, ct)
    finally:
        store.close()
        shutil.rmtree(tmp_path / "data", ignore_errors=True)


def test_upload_whose_voxels_fill_the_disk_gets_507_and_leaves_nothing(
    make_client, small_nifti: bytes, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The disk fills while the server writes the voxels (zarr's file writes say ENOSPC):
    507 with a JSON detail, no volume listed, no folder under volumes/ or tmp/."""
    import errno

    import zarr.storage._local as local

    client = make_client()
    written = []
    put = local._put

    def fill_up(*args, **kwargs):
        if len(written) >= 2:  # a few chunks made it: the volume is half-written then
            raise OSError(errno.ENOSPC, "No space left on device")
        written.append(args)
        return put(*args, **kwargs)

    monkeypatch.setattr(local, "_put", fill_up)
    r = client.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)})
    assert r.status_code == 507, r.text
    assert r.json()["detail"].startswith("disk full:"), r.text
    assert written, "the upload never reached the voxel writes"
    monkeypatch.undo()
    assert client.get("/api/volumes").json() == []
    data = Path(client.app.state.settings.data_dir)
    assert list((data / "volumes").iterdir()) == []
    assert list((data / "tmp").rglob("*")) == []
    r = client.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)})
    assert r.status_code == 201, r.text  # room again: stored


@pytest.mark.slow  # a real scan read lazily and meshed by a worker
def test_a_volume_over_the_in_memory_size_is_read_lazily_and_still_meshed(
    make_client, small_nifti: bytes, monkeypatch: pytest.MonkeyPatch, wait_done
) -> None:
    """MISS_IN_MEMORY_MAX_MB=0: every volume is a lazy zarr.Array; jobs (their worker
    reads the setting too) and slices work from the chunks."""
    from miss.server.storage.store import Store

    monkeypatch.setenv("MISS_IN_MEMORY_MAX_MB", "0")
    client = make_client(in_memory_max_mb=0)
    store: Store = client.app.state.store
    volume = client.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)}).json()
    assert not isinstance(store.open_volume(volume["id"]).data, np.ndarray)
    body = {"volume": volume["id"], "level": 0, "decimate": "none"}
    r = client.post("/api/models", json=body)
    assert r.status_code == 202, r.text
    model = wait_done(client, r.json()["id"])
    assert model["status"] == "done", model
    assert model["stats"]["triangles"] > 100
    r = client.get(f"/api/volumes/{volume['id']}/slices/axial/12.png")
    assert r.status_code == 200


def test_a_dask_worker_reads_chunks_without_loading_the_web_server() -> None:
    # every block task brings a volume on disk (this module's class) to a Dask worker:
    # unpickling it imported FastAPI, SQLAlchemy and the routes too (0.84 s in the
    # cluster's first job)
    code = (
        "import sys, miss.server.storage.chunked; "
        "print([m for m in ('fastapi', 'sqlalchemy', 'miss.server.app') if m in sys.modules])"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"
    from miss.server import Settings, create_app  # still there, loaded when asked for

    assert callable(create_app) and Settings.__name__ == "Settings"
