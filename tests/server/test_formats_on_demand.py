"""Formats when asked (issue 41): a job keeps the GLB and its scene in one internal form;
every other format is made on its first download, from that form, with the bytes the
writers make of the job's scene; then read from the model's folder, within a bounded
cache."""

from __future__ import annotations

import fcntl
import io
import json
import os
import threading
import zipfile
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from server.test_faults import (
    ball_nifti,
    can_mount_tmpfs,  # noqa: F401 - a fixture, used below
    fill,
    tmpfs_wrap,
    upload,
)
from support.models import wait_for_model
from support.realserver import serving
from test_x3d_schema import validate as x3d_errors

from miss.export import FORMATS, export
from miss.geometry import vertex_normals
from miss.pipeline import run
from miss.scene import Part, Scene
from miss.server import quota
from miss.server.core.settings import Settings
from miss.server.storage import formats
from miss.spec import JobSpec
from miss.types import Mesh

#: The demo phantom's bone, small enough to make in a few seconds.
JOB = {"level": 300, "sample_rate": 2}


def _scene() -> Scene:
    """Three parts: one with its own normals and face labels, one without either, one with
    the normals the writers would compute."""
    rng = np.random.default_rng(41)
    vertices = rng.normal(size=(50, 3)).astype(np.float32) * 20
    faces = rng.integers(0, 50, size=(80, 3)).astype(np.int32)
    normals = rng.normal(size=(50, 3)).astype(np.float32)
    labels = np.arange(80) % 3
    first = Part("skin (−400 HU)", Mesh(vertices, faces, normals, labels), (0.9, 0.7, 0.6), 0.5)
    second = Part("bone", Mesh(vertices[:30] * 0.5, faces[:40] % 30), (1.0, 1.0, 0.9), 1.0, 7)
    made = Mesh(vertices, faces[::-1], vertex_normals(vertices, faces[::-1]))
    return Scene((first, second, Part("made", made)), "a title", ("a note",))


@pytest.mark.parametrize("parts", [1, 3])
def test_the_stored_form_gives_every_writer_the_same_bytes(tmp_path: Path, parts: int) -> None:
    scene = Scene(_scene().parts[:parts], "a title", ("a note",))
    metadata = {"software": "MISS test", "created": "2026-11-28T12:00:00+00:00"}
    path = tmp_path / formats.MESH_FILE
    path.write_bytes(formats.scene_bytes(scene, "Head CT", metadata))
    stored = formats.read_scene(path)
    kept = set(zipfile.ZipFile(path).namelist())
    assert "n0.npy" in kept and "n2.npy" not in kept  # made again from the faces
    assert (stored.title, stored.metadata) == ("Head CT", metadata)
    for got, want in zip(stored.scene.parts, scene.parts, strict=True):
        for name in ("vertices", "faces", "normals", "labels"):
            a, b = getattr(got.mesh, name), getattr(want.mesh, name)
            assert (a is None) == (b is None)
            if a is not None:
                assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
    for fmt in FORMATS:
        made = export(stored.scene, fmt, title=stored.title, metadata=stored.metadata)
        assert made == export(scene, fmt, title="Head CT", metadata=metadata), fmt


@pytest.fixture(scope="module")
def job_scene(demo_file: Path) -> Scene:
    """The demo phantom's bone as a job builds it (in locality order)."""
    from miss.io import load_volume

    spec = JobSpec.of(levels=[JOB["level"]], sample_rate=JOB["sample_rate"])
    return run(load_volume(demo_file), spec, measure=False).scene


def _entries(data: bytes) -> dict[str, int]:
    """Each array's deflated bytes in an internal form."""
    with zipfile.ZipFile(io.BytesIO(data)) as archive:
        return {i.filename.removesuffix(".npy"): i.compress_size for i in archive.infolist()}


def test_a_jobs_faces_take_about_a_byte_a_triangle_in_the_stored_form(
    job_scene: Scene, tmp_path: Path
) -> None:
    """The faces of a job's scene go through meshoptimizer's index codec (with each
    triangle's turn): under 1.5 bytes a triangle, where deflating the int32 list took 3.3
    and more; the whole form under 5.5 bytes a triangle. Every array comes back exactly."""
    data = formats.scene_bytes(job_scene, "t", {})
    sizes = _entries(data)
    triangles = job_scene.n_triangles
    assert (sizes["f0"] + sizes.get("r0", 0)) / triangles < 1.5, sizes
    assert len(data) / triangles < 5.5, (len(data), triangles)
    path = tmp_path / formats.MESH_FILE
    path.write_bytes(data)
    back = formats.read_scene(path)
    want, got = job_scene.parts[0].mesh, back.scene.parts[0].mesh
    for name in ("vertices", "faces", "normals"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes(), name


def test_normals_a_few_bits_off_the_computed_ones_are_kept_as_their_xor(
    job_scene: Scene, tmp_path: Path
) -> None:
    mesh = job_scene.parts[0].mesh
    assert mesh.normals is not None
    off = mesh.normals.copy()
    off.view(np.uint32)[::7, 1] ^= 1  # the last bit of every seventh vertex's y
    scene = Scene((Part("bone", Mesh(mesh.vertices, mesh.faces, off)),), "t", ())
    path = tmp_path / formats.MESH_FILE
    path.write_bytes(formats.scene_bytes(scene, "t", {}))
    header = json.loads(np.load(path)["header"].tobytes())
    assert header["parts"][0]["normals"] == "xor"
    assert _entries(path.read_bytes())["n0"] < off.nbytes / 20  # mostly zero bits
    back = formats.read_scene(path).scene.parts[0].mesh.normals
    assert back is not None and back.tobytes() == off.tobytes()


def test_the_first_layouts_files_are_read_as_they_were(tmp_path: Path) -> None:
    """A model kept before version 2 (faces plain, normals stored or made again)."""
    scene = _scene()
    arrays: dict[str, np.ndarray] = {}
    parts = []
    for i, part in enumerate(scene.parts):
        mesh = part.mesh
        arrays[f"v{i}"], arrays[f"f{i}"] = mesh.vertices, mesh.faces
        kind = None if mesh.normals is None else "computed" if i == 2 else "stored"
        if kind == "stored":
            arrays[f"n{i}"] = mesh.normals
        if mesh.labels is not None:
            arrays[f"l{i}"] = mesh.labels
        parts.append({"name": part.name, "color": list(part.color), "opacity": part.opacity,
                      "label": part.label, "normals": kind})  # fmt: skip
    header = {"version": 1, "title": "old", "metadata": {}, "parts": parts,
              "scene_title": scene.title, "notes": list(scene.notes)}  # fmt: skip
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    path = tmp_path / "old.npz"
    np.savez_compressed(path, **arrays)  # type: ignore[arg-type]
    stored = formats.read_scene(path)
    for fmt in FORMATS:
        assert export(stored.scene, fmt, title="old") == export(scene, fmt, title="old"), fmt


def _store(client: TestClient) -> Any:
    return client.app.state.store


def _model(client: TestClient, demo_id: str, **job: Any) -> dict[str, Any]:
    r = client.post("/api/models", json={"volume": demo_id, **JOB, **job})
    assert r.status_code in (200, 202), r.text
    body = wait_for_model(client, r.json()["id"])
    assert body["status"] == "done", body
    return body


def _made(folder: Path, fmt: str) -> int:
    """How many times ``fmt`` was made in ``folder`` (its ``made.log``)."""
    log = folder / formats.MADE_LOG
    lines = log.read_text().splitlines() if log.exists() else []
    return sum(f" made {fmt}:" in line for line in lines)


def test_a_job_keeps_the_glb_and_its_scene_and_lists_the_rest_on_request(
    client: TestClient, demo_id: str
) -> None:
    body = _model(client, demo_id)
    folder = _store(client).model_dir(body["id"])
    on_disk = sorted(p.name for p in folder.iterdir() if p.name != "worker.log")
    assert on_disk == ["model.glb", formats.MESH_FILE]
    assert list(body["files"]) == FORMATS  # every format, in the formats' order
    glb = body["files"]["glb"]
    assert glb["on_request"] is False and glb["bytes"] == (folder / "model.glb").stat().st_size
    for fmt in formats.ON_REQUEST:
        entry = body["files"][fmt]
        assert entry["on_request"] is True and entry["bytes"] is None and entry["etag"] is None
        assert entry["url"] == f"/api/models/{body['id']}/model.{fmt}"


@pytest.mark.slow  # every format of a job; test_api downloads each in the fast lane
def test_every_download_has_the_bytes_the_writers_make_of_the_jobs_scene(
    client: TestClient, demo_id: str, tmp_path: Path
) -> None:
    """The scene computed again in this process, with the provenance the GLB carries,
    encoded by the writers: byte for byte what each download gives; the X3D passes its
    schema; the listing then gives each file's size and ETag."""
    body = _model(client, demo_id, decimate="quadric", reduce=0.5)
    store = _store(client)
    got = {}
    for fmt in FORMATS:
        r = client.get(f"/api/models/{body['id']}/model.{fmt}")
        assert r.status_code == 200, r.text
        got[fmt] = r.content
    glb_json = json.loads(got["glb"][20 : 20 + int.from_bytes(got["glb"][12:16], "little")])
    metadata = glb_json["asset"]["extras"]  # the provenance the job gave every writer
    volume = store.open_volume(demo_id)
    spec = JobSpec.from_dict({**store.get_model(body["id"]).spec, "formats": FORMATS})
    title = store.get_volume(demo_id).name
    again = run(volume, spec, title=title, metadata=metadata, measure=False)
    for fmt in formats.ON_REQUEST:
        assert got[fmt] == export(again.scene, fmt, title=title, metadata=metadata), fmt
    assert x3d_errors(got["x3d"]) == []
    listed = client.get(f"/api/models/{body['id']}").json()["files"]
    for fmt in FORMATS:
        assert listed[fmt]["bytes"] == len(got[fmt]), fmt
        r = client.get(listed[fmt]["url"], headers={"If-None-Match": f'"{listed[fmt]["etag"]}"'})
        assert r.status_code == 304, fmt


def test_a_second_download_reads_the_file_the_first_made(client: TestClient, demo_id: str) -> None:
    body = _model(client, demo_id, level=200)
    folder = _store(client).model_dir(body["id"])
    first = client.get(f"/api/models/{body['id']}/model.stl")
    inode = (folder / "model.stl").stat().st_ino
    second = client.get(f"/api/models/{body['id']}/model.stl")
    assert first.status_code == second.status_code == 200
    assert first.content == second.content
    assert (folder / "model.stl").stat().st_ino == inode  # not written again
    assert _made(folder, "stl") == 1


@pytest.mark.slow  # threads racing a writer
def test_downloads_asked_while_a_format_is_made_wait_for_its_one_writer(
    client: TestClient, demo_id: str
) -> None:
    """The test holds the format's lock (as a writer in another process would) while
    three downloads start; once it lets go, one of them makes the file, all get it."""
    body = _model(client, demo_id, level=250)
    folder = _store(client).model_dir(body["id"])
    url = f"/api/models/{body['id']}/model.obj"
    lock = os.open(folder / ".obj.lock", os.O_RDWR | os.O_CREAT, 0o600)
    fcntl.flock(lock, fcntl.LOCK_EX)
    with ThreadPoolExecutor(3) as pool:
        asked = [pool.submit(client.get, url) for _ in range(3)]
        threading.Event().wait(1.0)  # let them reach the lock
        assert not any(a.done() for a in asked)  # they wait for the writer
        assert not (folder / "model.obj").exists()
        os.close(lock)
        answers = [a.result() for a in asked]
    assert {r.status_code for r in answers} == {200}
    assert len({r.content for r in answers}) == 1
    assert _made(folder, "obj") == 1


def test_the_cache_removes_the_least_recently_used_made_files(tmp_path: Path) -> None:
    models = tmp_path / "models"
    sizes = {"a": ("stl", 100), "b": ("ply", 100), "c": ("obj", 100)}
    for when, (name, (fmt, size)) in enumerate(sizes.items()):
        folder = models / name
        folder.mkdir(parents=True)
        (folder / formats.MESH_FILE).write_bytes(b"m" * 1000)
        (folder / "model.glb").write_bytes(b"g" * 1000)
        (folder / f"model.{fmt}").write_bytes(b"x" * size)
        os.utime(folder / f"model.{fmt}", ns=(when * 10**9, when * 10**9))
    legacy = models / "legacy"  # an older model's files are its only copy
    legacy.mkdir()
    (legacy / "model.stl").write_bytes(b"y" * 1000)
    os.utime(legacy / "model.stl", ns=(0, 0))
    removed = formats.evict(models, cap=150)
    assert removed == [models / "a" / "model.stl", models / "b" / "model.ply"]
    assert (models / "c" / "model.obj").exists() and (legacy / "model.stl").exists()
    assert all((models / n / formats.MESH_FILE).exists() for n in "abc")
    assert all((models / n / "model.glb").exists() for n in "abc")


@pytest.mark.slow  # two jobs' formats made and made again
def test_over_the_cap_the_older_made_file_goes_and_is_made_again_the_same(
    make_client: Callable[..., TestClient],
) -> None:
    client = make_client(demo=True, format_cache_mb=1e-6)  # one byte: only the newest stays
    demo = client.get("/api/volumes").json()[0]["id"]
    body = _model(client, demo)
    folder = _store(client).model_dir(body["id"])
    stl = client.get(f"/api/models/{body['id']}/model.stl").content
    client.get(f"/api/models/{body['id']}/model.ply")
    assert (folder / "model.ply").exists() and not (folder / "model.stl").exists()
    assert (folder / "model.glb").exists() and (folder / formats.MESH_FILE).exists()
    assert client.get(f"/api/models/{body['id']}/model.stl").content == stl
    assert _made(folder, "stl") == 2


def test_made_formats_count_in_the_quota_and_go_with_their_model(
    client: TestClient, demo_id: str
) -> None:
    body = _model(client, demo_id, level=350)
    store = _store(client)
    folder = store.model_dir(body["id"])
    before = quota.folder_bytes(folder, quota.NOT_COUNTED)
    size = len(client.get(f"/api/models/{body['id']}/model.wrl").content)
    assert quota.folder_bytes(folder, quota.NOT_COUNTED) >= before + size
    assert client.delete(f"/api/models/{body['id']}").status_code == 204
    assert not folder.exists()


def test_the_cache_setting_is_checked() -> None:
    assert Settings.from_env({"MISS_FORMAT_CACHE_MB": "0"}).format_cache_bytes == 0
    assert Settings().format_cache_bytes == 2048 * 2**20
    with pytest.raises(ValueError, match="MISS_FORMAT_CACHE_MB"):
        Settings.from_env({"MISS_FORMAT_CACHE_MB": "-1"})


@pytest.mark.slow  # a tmpfs mounted for the job
@pytest.mark.usefixtures("can_mount_tmpfs")
def test_a_format_that_does_not_fit_on_the_disk_gives_507_and_leaves_nothing(
    tmp_path: Path,
) -> None:
    """The data folder on a real 32 MB tmpfs, filled but for less than the OBJ needs:
    507 naming the problem and the fix, no file left; with room again, the OBJ."""
    data = tmp_path / "data"
    data.mkdir()
    env = {"MISS_DEMO": "0", "MISS_MIN_FREE_MB": "1"}
    with serving(data, tmp_path / "server.log", env=env, wrap=tmpfs_wrap(data, 32)) as server:
        inside = server.path(data)
        volume = upload(server, ball_nifti((96, 96, 96)), "ball.nii.gz")
        job = server.submit(volume, level=0, sample_rate=1, decimate="none")
        assert server.wait(job, ("done", "failed"))["status"] == "done"
        folder = inside / "models" / job
        kept = sorted(p.name for p in folder.iterdir())
        fill(inside / "filler", leave=200 * 1024)  # the OBJ is about 2 MB
        r = server.http.get(f"/api/models/{job}/model.obj")
        assert r.status_code == 507, r.text
        detail = r.json()["detail"]
        assert detail.startswith("disk full") and "free space" in detail, detail
        assert sorted(p.name for p in folder.iterdir() if p.suffix != ".lock") == kept
        (inside / "filler").unlink()
        r = server.http.get(f"/api/models/{job}/model.obj")
        assert r.status_code == 200 and len(r.content) > 1_000_000, r.text
