"""A label map laid over an uploaded volume: upload, listing, jobs on chosen labels."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

CT, SEG = "example_ct.nii.gz", "example_seg.nii.gz"


def _upload_map(client: TestClient, volume_id: str, content: bytes, name: str, **kw: Any) -> Any:
    return client.post(f"/api/volumes/{volume_id}/labelmap", files={"file": (name, content)}, **kw)


def test_labelmap_upload_generate_delete(
    client: TestClient,
    datasets: Path,
    people: dict[str, dict[str, str]],
    small_nifti: bytes,
    upload_for: Callable[..., dict[str, Any]],
    wait_done: Callable[..., dict[str, Any]],
) -> None:
    folder = datasets / "ct_abdomen_totalseg"
    alice, bob = people["alice"], people["bob"]
    volume = upload_for(client, alice, (folder / CT).read_bytes(), CT)
    vid = volume["id"]
    assert client.get(f"/api/volumes/{vid}", headers=alice).json()["labelmap"] is None

    # another user sees no such volume; a float (CT) volume is no label map
    seg = (folder / SEG).read_bytes()
    assert _upload_map(client, vid, seg, SEG, headers=bob).status_code == 404
    r = _upload_map(client, vid, (folder / CT).read_bytes(), CT, headers=alice)
    assert r.status_code == 422 and "not a label map" in r.json()["detail"], r.text
    # a label map somewhere else in patient space does not overlap the volume
    r = _upload_map(client, vid, small_nifti, "ball.nii.gz", headers=alice)
    assert r.status_code == 422, r.text

    r = _upload_map(client, vid, seg, SEG, headers=alice)
    assert r.status_code == 200, r.text
    labels = client.get(f"/api/volumes/{vid}", headers=alice).json()["labelmap"]["labels"]
    assert len(labels) == 41
    names = {e["label"]: e["name"] for e in labels}
    assert names[1] == "spleen" and names[5] == "liver"
    assert all(e["voxels"] > 0 for e in labels)

    body = {"volume": vid, "labels": [1, 5], "sample_rate": 1, "decimate": "quadric"}
    r = client.post("/api/models", json=body, headers=alice)
    assert r.status_code == 202, r.text
    model = wait_done(client, r.json()["id"])
    assert model["status"] == "done", model
    parts = [p["name"] for p in model["stats"]["parts"]]
    assert sorted(parts) == ["liver", "spleen"]
    # a plain job on the same volume is another model
    plain = client.post("/api/models", json={"volume": vid, "level": 300}, headers=alice)
    assert plain.json()["id"] != model["id"]

    assert client.delete(f"/api/volumes/{vid}/labelmap", headers=bob).status_code == 404
    assert client.delete(f"/api/volumes/{vid}/labelmap", headers=alice).status_code == 204
    assert client.get(f"/api/volumes/{vid}", headers=alice).json()["labelmap"] is None
    assert client.delete(f"/api/volumes/{vid}/labelmap", headers=alice).status_code == 404
    r = client.post("/api/models", json=body, headers=alice)
    assert r.status_code == 422, r.text  # a CT without a label map has no labels
