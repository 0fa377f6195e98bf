"""Files other tools open (issue 42): a multi-part model's STL, PLY and OBJ downloads are
each one file of their format (they were zips served as ``model/stl`` etc., which trimesh
opened as empty scenes), and a plain GLB, with no required glTF extension, is offered
beside the meshopt-compressed one the viewer draws."""

from __future__ import annotations

import io
import json
import zipfile
from typing import Any

import pytest
import trimesh
from fastapi.testclient import TestClient
from support.models import wait_for_model
from test_gltf_validator import Validate, assert_valid
from test_gltf_validator import validate as validate  # noqa: F401 - a fixture, used below

#: Two levels of the demo phantom: translucent skin and bone, two parts.
JOB = {"levels": [-500, 300], "sample_rate": 2}


@pytest.fixture(scope="module")
def two_parts(client: TestClient) -> dict[str, Any]:
    volumes = client.get("/api/volumes").json()
    demo = next(v["id"] for v in volumes if v["name"] == "Demo head phantom (synthetic CT)")
    r = client.post("/api/models", json={"volume": demo, **JOB})
    assert r.status_code in (200, 202), r.text
    body = wait_for_model(client, r.json()["id"])
    assert body["status"] == "done", body
    return body


def _glb_json(data: bytes) -> dict[str, Any]:
    """The JSON chunk of a GLB (12-byte header, then the chunk's length and type)."""
    return json.loads(data[20 : 20 + int.from_bytes(data[12:16], "little")])


def _download(client: TestClient, body: dict[str, Any], fmt: str) -> bytes:
    r = client.get(body["files"][fmt]["url"])
    assert r.status_code == 200, r.text
    return r.content


@pytest.mark.parametrize("fmt", ["stl", "ply", "obj"])
def test_a_two_part_download_is_one_file_trimesh_reads_whole(
    client: TestClient, two_parts: dict[str, Any], fmt: str
) -> None:
    url = two_parts["files"][fmt]["url"]
    r = client.get(url)
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == f"model/{fmt}"
    assert r.headers["content-disposition"].endswith(f'.{fmt}"')
    assert r.content[:2] != b"PK"  # not a zip under another name
    loaded = trimesh.load(io.BytesIO(r.content), file_type=fmt, process=False, split_objects=True)
    meshes = loaded.geometry if isinstance(loaded, trimesh.Scene) else {"": loaded}
    triangles = {p["name"]: p["triangles"] for p in two_parts["stats"]["parts"]}
    assert sum(len(m.faces) for m in meshes.values()) == sum(triangles.values())
    if fmt == "obj":  # a group per part, named after it
        names = {"skin_500_HU": "skin (-500 HU)", "bone_300_HU": "bone (300 HU)"}
        got = {names[k]: len(m.faces) for k, m in meshes.items()}
        assert got == triangles
    listed = client.get(f"/api/models/{two_parts['id']}").json()["files"][fmt]
    assert listed["mime"] == f"model/{fmt}" and listed["bytes"] == len(r.content)


def test_the_plain_glb_opens_anywhere_beside_the_compressed_one(
    client: TestClient, two_parts: dict[str, Any], validate: Validate
) -> None:
    entry = two_parts["files"]["plain.glb"]
    assert entry["label"] == "GLB (plain, opens anywhere)"
    assert two_parts["files"]["glb"]["label"] == ".glb"
    r = client.get(entry["url"])
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "model/gltf-binary"
    assert r.headers["content-disposition"].endswith('.plain.glb"')
    plain, compressed = r.content, _download(client, two_parts, "glb")
    document = _glb_json(plain)
    assert "extensionsRequired" not in document and "extensionsUsed" not in document
    assert {a["componentType"] for a in document["accessors"] if a["type"] == "VEC3"} == {5126}
    assert "EXT_meshopt_compression" in _glb_json(compressed)["extensionsRequired"]  # viewer's
    loaded = trimesh.load(io.BytesIO(plain), file_type="glb", process=False)
    triangles = {p["name"]: p["triangles"] for p in two_parts["stats"]["parts"]}
    assert {k: len(m.faces) for k, m in loaded.geometry.items()} == triangles
    colours = [m["pbrMetallicRoughness"]["baseColorFactor"] for m in document["materials"]]
    assert colours[0][3] == pytest.approx(0.35) and colours[1][3] == 1.0  # translucent skin
    assert_valid(validate({"plain": plain}))


def test_a_zip_made_before_is_made_again_as_one_file(
    client: TestClient, two_parts: dict[str, Any]
) -> None:
    """A data folder from before: its made ``model.stl`` a zip of one STL per part, listed
    as ``application/zip``. The next download makes the one-solid STL in its place."""
    store = client.app.state.store
    model_id = two_parts["id"]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("1_skin.stl", b"old")
        archive.writestr("scene.json", b"{}")
    old = buffer.getvalue()
    (store.model_dir(model_id) / "model.stl").write_bytes(old)
    files = dict(store.get_model(model_id).files)
    files["stl"] = {**files["stl"], "bytes": len(old), "etag": "0" * 32, "mime": "application/zip"}
    store.update_model(model_id, files=files)
    data = _download(client, client.get(f"/api/models/{model_id}").json(), "stl")
    assert data[:2] != b"PK"
    solid = trimesh.load(io.BytesIO(data), file_type="stl", process=False)
    assert len(solid.faces) == two_parts["stats"]["triangles"]
    listed = client.get(f"/api/models/{model_id}").json()["files"]["stl"]
    assert listed["mime"] == "model/stl" and listed["bytes"] == len(data)


def test_a_pacs_send_still_has_one_stl_a_part(
    client: TestClient, two_parts: dict[str, Any]
) -> None:
    """The download's STL is one solid now; what goes to the PACS is still one
    Encapsulated STL a part, named, from the model's stored scene."""
    from miss.server.pacs_exchange import stl_parts

    parts = stl_parts(client.app.state.store.model_dir(two_parts["id"]))
    want = [(p["name"], p["triangles"]) for p in two_parts["stats"]["parts"]]
    got = [(name, int.from_bytes(stl[80:84], "little")) for name, stl in parts]
    assert got == want and all(
        len(stl) == 84 + 50 * n for (_, stl), (_, n) in zip(parts, got, strict=True)
    )
