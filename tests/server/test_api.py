"""The REST API through FastAPI's TestClient: every status code path, real scans, real jobs."""

from __future__ import annotations

import gzip
import io
import json
import os
import signal
import stat
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh
from fastapi.testclient import TestClient
from lxml import etree
from PIL import Image
from support.pg import settings_for

from miss.server.app import create_app
from miss.server.core.assets import MODULES, WEB
from miss.server.storage import chunked

DEMO = "Demo head phantom (synthetic CT)"
FAST = {"level": 300, "sample_rate": 4, "decimate": "none"}
TINT = np.array([255, 96, 32])


def leftovers(data: Path) -> list[str]:
    """Anything an upload or job may have left in tmp/."""
    return sorted(p.name for p in (data / "tmp").iterdir())


def upload(client: TestClient, filename: str, content: bytes, **fields: str) -> object:
    return client.post("/api/volumes", files={"file": (filename, content)}, data=fields)


def zip_bytes(members: dict[str, bytes], symlink: str | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
        if symlink:
            info = zipfile.ZipInfo(symlink)
            info.create_system = 3
            info.external_attr = (stat.S_IFLNK | 0o777) << 16
            zf.writestr(info, "/etc/passwd")
    return buf.getvalue()


# -- volumes ------------------------------------------------------------------------------


def test_demo_volume_registered_once(data_dir: Path, login, admin_password: str) -> None:
    settings = settings_for(data_dir, admin_password=admin_password)
    with TestClient(create_app(settings)) as c:
        volumes = login(c).get("/api/volumes").json()
    assert [v["name"] for v in volumes] == [DEMO]
    demo = volumes[0]
    assert demo["dims"] == [128, 128, 128] and demo["modality"] == "CT" and demo["units"] == "HU"
    assert {p["name"]: p["level"] for p in demo["presets"]} == {"bone": 300, "skin": -500}
    with TestClient(create_app(settings)) as c:  # a restart does not add a second demo
        assert len(login(c).get("/api/volumes").json()) == 1


def test_demo_registered_on_empty_store(make_client) -> None:
    c = make_client(demo=True)
    assert [v["name"] for v in c.get("/api/volumes").json()] == [DEMO]


def test_upload_zipped_dicom_series(client: TestClient, dicom_zip: Path) -> None:
    r = upload(client, dicom_zip.name, dicom_zip.read_bytes())
    assert r.status_code == 201, r.text
    body = r.json()
    assert r.headers["location"] == f"/api/volumes/{body['id']}"
    # Named by what the scan says (no series description here), never by its file.
    assert body["name"].startswith("CT HEAD volume, uploaded ")
    assert body["modality"] == "CT" and body["units"] == "HU"
    assert body["dims"][:2] == [512, 512] and body["dims"][2] >= 28
    assert body["series"][0]["slices"] == 28
    data = Path(client.app.state.settings.data_dir)
    stored = data / "volumes" / body["id"]
    assert sorted(p.name for p in stored.iterdir()) == [
        "data.zarr",
        "histogram.json",
        "meta.json",
        "thumbnail.png",
    ]
    voxels, affine, _ = chunked.open_array(stored / "data.zarr")
    assert list(voxels.shape) == body["dims"]
    meta = json.loads((stored / "meta.json").read_text())
    assert affine.tolist() == meta["affine"]
    assert "patient" not in meta and len(meta["affine"]) == 4
    assert leftovers(data) == []
    # Physical aspect: 512 x 0.49 mm across, ~38 x 3.9 mm down on the sagittal view.
    png = client.get(f"/api/volumes/{body['id']}/slices/sagittal/256.png")
    w, h = Image.open(io.BytesIO(png.content)).size
    view = body["views"]["sagittal"]
    assert w / h == pytest.approx(view["width_mm"] / view["height_mm"], rel=0.02)


def test_upload_nifti(client: TestClient, datasets: Path) -> None:
    path = datasets / "nifti" / "CT_pitch.nii.gz"
    r = upload(client, path.name, path.read_bytes(), name="Pitched head CT")
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["name"] == "Pitched head CT"
    assert body["dims"] == [175, 248, 58] and body["range"] == [0.0, 255.0]
    assert body["spacing"] == pytest.approx([0.8125, 0.8125, 2.397], abs=1e-3)
    skin, tissue = (
        next(p["level"] for p in body["presets"] if p["name"] == n) for n in ("skin", "tissue")
    )
    # a windowed 8-bit CT: no modality and no CT values, so intensities from the histogram
    assert 0 < skin < tissue < 255
    assert client.get(f"/api/volumes/{body['id']}").json()["id"] == body["id"]


def test_list_get_delete(client: TestClient, demo_id: str, datasets: Path) -> None:
    path = datasets / "nifti" / "CT_pitch.nii.gz"
    new = upload(client, path.name, path.read_bytes()).json()["id"]
    assert new in [v["id"] for v in client.get("/api/volumes").json()]
    model = client.post(
        "/api/models", json={"volume": new, "level": 100, "sample_rate": 4, "decimate": "none"}
    )
    assert model.status_code == 202, model.text
    assert client.delete(f"/api/volumes/{new}").status_code == 204
    assert client.get(f"/api/volumes/{new}").status_code == 404
    assert client.get(f"/api/models/{model.json()['id']}").status_code == 404
    assert client.delete(f"/api/volumes/{new}").status_code == 404
    data = Path(client.app.state.settings.data_dir)
    assert (
        not (data / "volumes" / new).exists()
        and not (data / "models" / model.json()["id"]).exists()
    )
    assert client.get(f"/api/volumes/{demo_id}").status_code == 200


def test_slices_window_threshold_and_bounds(client: TestClient, demo_id: str) -> None:
    base = f"/api/volumes/{demo_id}/slices"
    for axis in ("axial", "coronal", "sagittal"):
        r = client.get(f"{base}/{axis}/64.png", params={"window": 2000, "level": 0})
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        assert Image.open(io.BytesIO(r.content)).size == (128, 128)
    grey = Image.open(io.BytesIO(client.get(f"{base}/axial/64.png").content))
    assert grey.mode == "L"  # no tint asked for: one channel
    plain = np.asarray(grey.convert("RGB"))
    tinted = np.asarray(
        Image.open(io.BytesIO(client.get(f"{base}/axial/64.png?threshold=300").content))
    )
    orange = (tinted[..., 0] > tinted[..., 2] + 60).sum()
    assert orange > 100 and (plain[..., 0] == plain[..., 2]).all()  # the skull ring, tinted
    # Sagittal: superior is up, so the top rows of a mid-sagittal slice hold skull, the
    # bottom rows below the head only air.
    sag = np.asarray(
        Image.open(io.BytesIO(client.get(f"{base}/sagittal/64.png?threshold=300").content))
    )
    assert (sag[:20, :, 0] > sag[:20, :, 2] + 60).any() and sag[-3:].max() < 40
    r = client.get(f"{base}/axial/128.png")
    assert r.status_code == 404 and "outside 0..127" in r.json()["detail"]
    assert client.get(f"{base}/axial/-1.png").status_code == 404
    assert client.get(f"{base}/oblique/3.png").status_code == 422
    assert client.get(f"{base}/axial/three.png").status_code == 422
    r = client.get(f"{base}/axial/3.png", params={"window": 0})
    assert r.status_code == 422 and "window" in r.json()["detail"]
    assert client.get("/api/volumes/nope/slices/axial/3.png").status_code == 404


def test_thumbnail_and_histogram(client: TestClient, demo_id: str) -> None:
    r = client.get(f"/api/volumes/{demo_id}/thumbnail.png")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert max(Image.open(io.BytesIO(r.content)).size) <= 160
    h = client.get(f"/api/volumes/{demo_id}/histogram").json()
    assert len(h["edges"]) == len(h["counts"]) + 1 == len(h["bins"]) + 1
    assert sum(h["counts"]) == 128**3
    assert {p["name"]: p["level"] for p in h["presets"]} == {"bone": 300.0, "skin": -500.0}
    assert client.get("/api/volumes/nope/histogram").status_code == 404
    assert client.get("/api/volumes/nope/thumbnail.png").status_code == 404


# -- bad uploads --------------------------------------------------------------------------


def _nifti_like() -> bytes:
    return b"\x00" * 2048


BAD_UPLOADS = [
    ("not-a-zip", "series.zip", b"this is plain text, not an archive", 422, "zip"),
    ("corrupt-zip", "series.zip", None, 422, "zip"),
    ("dotdot", "evil.zip", zip_bytes({"../escape.dcm": b"x" * 200}), 422, ".."),
    ("absolute", "evil.zip", zip_bytes({"/etc/cron.d/x": b"x"}), 422, "absolute"),
    ("symlink", "evil.zip", zip_bytes({"a.dcm": b"x"}, symlink="link.dcm"), 422, "symbolic link"),
    ("empty-zip", "empty.zip", zip_bytes({}), 422, "empty"),
    ("text-file", "notes.txt", b"hello, this is not a scan\n" * 20, (415, 422), ""),
    ("png-image", "photo.png", b"\x89PNG\r\n\x1a\n" + b"\x00" * 100, (415, 422), ""),
    ("bad-nifti", "scan.nii", _nifti_like(), 422, "scan.nii"),
    ("empty-file", "scan.nii.gz", b"", 422, "empty"),
]


@pytest.mark.parametrize(
    ("case", "name", "content", "code", "words"), BAD_UPLOADS, ids=[b[0] for b in BAD_UPLOADS]
)
def test_bad_uploads_are_4xx_and_leave_nothing(
    client: TestClient,
    dicom_zip: Path,
    case: str,
    name: str,
    content: bytes | None,
    code: int | tuple[int, ...],
    words: str,
) -> None:
    if content is None:
        content = dicom_zip.read_bytes()[: dicom_zip.stat().st_size // 2]  # truncated
    data = Path(client.app.state.settings.data_dir)
    before = sorted(p.name for p in (data / "volumes").iterdir())
    r = upload(client, name, content)
    assert r.status_code in (code if isinstance(code, tuple) else (code,)), r.text
    detail = r.json()["detail"]
    assert isinstance(detail, str) and words.lower() in detail.lower()
    assert sorted(p.name for p in (data / "volumes").iterdir()) == before
    assert leftovers(data) == []


def test_upload_request_shape_errors(client: TestClient) -> None:
    r = client.post("/api/volumes", json={"file": "x"})
    assert r.status_code == 415 and "multipart" in r.json()["detail"]
    r = client.post("/api/volumes", data={"name": "no file"}, files={"other": ("a.txt", b"x")})
    assert r.status_code == 422 and "'file'" in r.json()["detail"]


def test_upload_over_size_limit(make_client) -> None:
    c = make_client(max_upload_mb=0.05)
    r = upload(c, "big.nii", b"\x00" * 100_000)
    assert r.status_code == 413 and "MISS_MAX_UPLOAD_MB" in r.json()["detail"]
    assert leftovers(Path(c.app.state.settings.data_dir)) == []


def test_zip_bomb_stops_at_unzipped_limit(make_client) -> None:
    c = make_client(max_unzipped_mb=1)
    bomb = zip_bytes({"slices/a.dcm": b"\x00" * (8 << 20)})
    assert len(bomb) < 64 << 10  # highly compressible: a small upload, 8 MB unpacked
    r = upload(c, "bomb.zip", bomb)
    assert r.status_code == 413 and "unzipped" in r.json()["detail"]
    # The declared sizes can lie: lower them and the byte count while unpacking still stops it.
    lying = bytearray(bomb)
    for header in (b"PK\x03\x04", b"PK\x01\x02"):
        at = lying.find(header)
        offset = 22 if header == b"PK\x03\x04" else 24
        lying[at + offset : at + offset + 4] = (100).to_bytes(4, "little")
    r = upload(c, "bomb.zip", bytes(lying))
    assert r.status_code in (413, 422), r.text
    assert leftovers(Path(c.app.state.settings.data_dir)) == []
    assert list((Path(c.app.state.settings.data_dir) / "volumes").iterdir()) == []


# -- models -------------------------------------------------------------------------------


def check_download(fmt: str, content: bytes, triangles: int) -> None:
    """Parse each format with an independent reader."""
    if fmt == "glb":  # served meshopt-compressed: read the glTF JSON chunk itself
        assert content[:4] == b"glTF"
        length = int.from_bytes(content[12:16], "little")
        document = json.loads(content[20 : 20 + length])
        assert "EXT_meshopt_compression" in document["extensionsRequired"]
        prims = [p for m in document["meshes"] for p in m["primitives"]]
        assert sum(document["accessors"][p["indices"]]["count"] for p in prims) == 3 * triangles
    elif fmt in ("stl", "ply", "obj"):
        mesh = trimesh.load(io.BytesIO(content), file_type=fmt, force="mesh", process=False)
        assert len(mesh.faces) == triangles
    elif fmt == "3mf":  # a zip of the OPC parts; tests/test_export_3mf.py reads it with lib3mf
        mesh = trimesh.load(io.BytesIO(content), file_type="3mf", force="mesh", process=False)
        assert len(mesh.faces) == triangles
    elif fmt == "x3d":
        root = etree.fromstring(content)
        assert root.tag == "X3D" and root.find(".//Shape") is not None
    else:
        text = (gzip.decompress(content) if fmt == "wrz" else content).decode("utf-8")
        assert text.startswith("#VRML V2.0 utf8")
        assert text.count("[") == text.count("]") > 0 and text.count("{") == text.count("}") > 0


MIMES = {
    "wrl": "model/vrml",
    "wrz": "model/vrml",
    "x3d": "model/x3d+xml",
    "glb": "model/gltf-binary",
    "stl": "model/stl",
    "ply": "model/ply",
    "obj": "model/obj",
    "3mf": "model/3mf",
}


def test_job_runs_and_every_format_downloads(client: TestClient, demo_id: str, wait_done) -> None:
    r = client.post("/api/models", json={"volume": demo_id, "level": 300, "sample_rate": 2})
    assert r.status_code == 202 and r.json()["status"] == "queued", r.text
    model_id = r.json()["id"]
    early = client.get(f"/api/models/{model_id}/model.glb")
    assert early.status_code == 409 and "done" in early.json()["detail"]
    body = wait_done(client, model_id)
    assert body["status"] == "done", body
    stats = body["stats"]
    assert stats["triangles"] > 1000 and set(stats["bytes"]) == {"glb"}  # the rest on request
    assert {"surface", "decimate", "write"} <= set(stats["seconds"]) and stats["max_error_mm"] >= 0
    for fmt, mime in MIMES.items():
        r = client.get(f"/api/models/{model_id}/model.{fmt}")
        assert r.status_code == 200
        assert r.headers["content-type"].split(";")[0] == mime
        assert (
            r.headers["content-disposition"]
            == f'attachment; filename="demo-head_level300_bone_sr2.{fmt}"'
        )
        assert r.headers["etag"] and "max-age" in r.headers["cache-control"]
        listed = client.get(f"/api/models/{model_id}").json()["files"][fmt]  # made now
        assert len(r.content) == listed["bytes"] and r.headers["etag"] == f'"{listed["etag"]}"'
        assert body["files"][fmt]["bytes"] == (len(r.content) if fmt == "glb" else None)
        check_download(fmt, r.content, stats["triangles"])
        again = client.get(
            f"/api/models/{model_id}/model.{fmt}", headers={"If-None-Match": r.headers["etag"]}
        )
        assert again.status_code == 304 and again.content == b""
    legacy = client.get(f"/api/models/{model_id}/model.wrl", headers={"Accept": "x-world/x-vrml"})
    assert legacy.headers["content-type"].startswith("x-world/x-vrml")
    assert client.get(f"/api/models/{model_id}/model.dxf").status_code == 404
    assert client.get("/api/models/nope/model.glb").status_code == 404
    # Identical parameters: the same model, at once.
    same = client.post(
        "/api/models", json={"volume": demo_id, "level": 300.0, "sample_rate": [2, 2, 2]}
    )
    assert (
        same.status_code == 200
        and same.json()["id"] == model_id
        and same.json()["status"] == "done"
    )
    listed = client.get("/api/models", params={"volume": demo_id}).json()
    assert model_id in [m["id"] for m in listed]
    assert client.get("/api/models", params={"volume": "nope"}).status_code == 404


def test_events_stream_until_done(client: TestClient, demo_id: str) -> None:
    r = client.post("/api/models", json={"volume": demo_id, **FAST, "level": 250})
    model_id = r.json()["id"]
    statuses = []
    with client.stream("GET", f"/api/models/{model_id}/events") as events:
        assert events.headers["content-type"].startswith("text/event-stream")
        for line in events.iter_lines():
            if line.startswith("data:"):
                statuses.append(json.loads(line[5:])["status"])
    assert statuses[-1] == "done" and set(statuses) <= {"queued", "running", "done"}
    assert client.get("/api/models/nope/events").status_code == 404


BAD_PARAMS = [
    ({"level": 5000}, 422, "outside this volume's values"),
    ({"level": 300, "end_slice": 500}, 422, "beyond the volume's 128 slices"),
    ({"level": 300, "start_slice": 50, "end_slice": 10}, 422, "swap"),
    (
        {"level": 300, "start_slice": 1, "end_slice": 8},
        422,
        "no surface at level 300 in slices 1..8",
    ),
    ({"level": 300, "sample_rate": 0}, 422, "sample_rate"),
    ({"level": 300, "sample_rate": 200}, 422, "at least 2"),
    ({"level": 300, "decimate": "magic"}, 422, "decimate"),
    ({"level": 300, "reduce": 1.5}, 422, "reduce"),
    ({"level": 300, "colour": "red"}, 422, "colour"),
    ({"sample_rate": 2}, 422, "level"),
    ({"level": "bone"}, 422, "level"),
]


@pytest.mark.parametrize(("params", "code", "words"), BAD_PARAMS)
def test_bad_model_parameters(
    client: TestClient, demo_id: str, params: dict, code: int, words: str
) -> None:
    r = client.post("/api/models", json={"volume": demo_id, **params})
    assert r.status_code == code, r.text
    assert isinstance(r.json()["detail"], str) and words in r.json()["detail"]


def test_unknown_ids(client: TestClient) -> None:
    r = client.post("/api/models", json={"volume": "nope", "level": 1})
    assert r.status_code == 404 and "GET /api/volumes" in r.json()["detail"]
    for path in ("/api/volumes/nope", "/api/models/nope"):
        assert client.get(path).status_code == 404
        assert client.delete(path).status_code == 404


@pytest.mark.slow
def test_worker_crash_fails_only_that_job(client: TestClient, demo_id: str, wait_done) -> None:
    r = client.post("/api/models", json={"volume": demo_id, **FAST, "level": 310})
    model_id = r.json()["id"]
    store = client.app.state.store
    deadline = time.monotonic() + 30
    while (pid := store.get_model(model_id).pid) is None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert pid is not None
    os.kill(pid, signal.SIGSEGV)  # what a crash in native code looks like from outside
    body = wait_done(client, model_id)
    assert body["status"] == "failed" and "worker crashed with signal 11 (SIGSEGV)" in body["error"]
    assert client.get("/api/health").json()["status"] == "ok"
    # Submitting the same parameters again retries the failed model.
    again = client.post("/api/models", json={"volume": demo_id, **FAST, "level": 310})
    assert again.json()["id"] == model_id and again.status_code == 202
    assert wait_done(client, model_id)["status"] == "done"
    assert client.delete(f"/api/models/{model_id}").status_code == 204
    assert client.get(f"/api/models/{model_id}").status_code == 404


# -- pages --------------------------------------------------------------------------------


def test_pages_static_and_docs(client: TestClient) -> None:
    for url, page in (
        ("/", "index.html"),
        ("/volumes/x", "volume.html"),
        ("/models/x", "model.html"),
    ):
        r = client.get(url)
        if (WEB / page).is_file():
            assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        else:
            assert r.status_code == 404 and page in r.json()["detail"]
    assert client.get("/static/nothing-here.js").status_code == 404
    assert client.get("/static/../server/app.py").status_code == 404
    assert client.get("/static/node_modules/three/package.json").status_code == 404
    three = client.get("/vendor/three/package.json")
    assert three.status_code == (200 if (MODULES / "three").is_dir() else 404)
    assert client.get("/vendor/three/../../package.json").status_code == 404
    assert client.get("/docs").status_code == 200
    assert "/api/models/{model_id}/model.{fmt}" in client.get("/openapi.json").json()["paths"]
