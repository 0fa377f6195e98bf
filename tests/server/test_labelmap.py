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


def test_label_map_colours_the_slices_and_names_a_voxel(
    client: TestClient,
    datasets: Path,
    people: dict[str, dict[str, str]],
    upload_for: Callable[..., dict[str, Any]],
) -> None:
    """Before any model: a slice asked ``labels=true`` shows the liver in the liver's colour
    (a plain slice is grey there), and ``/voxel`` gives a liver voxel's CT value as the
    file holds it (read here by nibabel) with the label's name."""
    import io

    import nibabel as nib
    import numpy as np
    from PIL import Image

    folder = datasets / "ct_abdomen_totalseg"
    alice = people["alice"]
    vid = upload_for(client, alice, (folder / CT).read_bytes(), CT)["id"]
    meta = _upload_map(client, vid, (folder / SEG).read_bytes(), SEG, headers=alice).json()
    liver = next(e for e in meta["labelmap"]["labels"] if e["name"] == "liver")
    seg = np.asarray(nib.load(folder / SEG).dataobj)
    ct = np.asarray(nib.load(folder / CT).get_fdata())
    i, j, k = (int(np.median(a)) for a in np.nonzero(seg == liver["label"]))
    while seg[i, j, k] != liver["label"]:  # the median point may fall outside: step inwards
        i, j, k = (int(a[0]) for a in np.nonzero(seg == liver["label"]))

    r = client.get(f"/api/volumes/{vid}/voxel?i={i}&j={j}&k={k}", headers=alice)
    assert r.status_code == 200, r.text
    got = r.json()
    assert got["label"] == liver["label"] and got["name"] == "liver"
    assert got["value"] == float(ct[i, j, k]) and got["units"] == "HU"
    r = client.get(f"/api/volumes/{vid}/voxel?i=0&j=0&k={ct.shape[2]}", headers=alice)
    assert r.status_code == 404 and "outside" in r.json()["detail"]

    def picture(query: str) -> np.ndarray:
        r = client.get(f"/api/volumes/{vid}/slices/axial/{k}.png?{query}", headers=alice)
        assert r.status_code == 200, r.text
        return np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB"), dtype=float)

    coloured, plain = picture("labels=true&window=400&level=40"), picture("window=400&level=40")
    changed = np.abs(coloured - plain).max(axis=2) > 10  # where a label lies
    # each changed pixel is the grey blended with a label's own colour (45 % of it)
    implied = (coloured[changed] - 0.55 * plain[changed]) / 0.45
    table = 255 * np.asarray([e["color"] for e in meta["labelmap"]["labels"]])
    gaps = np.linalg.norm(implied[:, None, :] - table[None, :, :], axis=2)
    assert np.median(gaps.min(axis=1)) < 6  # edges blur where the picture is resized
    nearest = [meta["labelmap"]["labels"][n]["name"] for n in gaps.argmin(axis=1)]
    assert nearest.count("liver") > 500
