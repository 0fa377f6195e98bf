"""The voxels sent to the browser's volume renderer (``/api/volumes/{id}/voxels``): small
enough, placed right, values that round-trip, cacheable for good, and for the owner only."""

from __future__ import annotations

import gzip
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
from fastapi.testclient import TestClient

from miss.server.volumes import voxels

#: Bright cube of the synthetic scan, voxel index ranges.
CUBE = (slice(10, 20), slice(12, 22), slice(5, 15))


@pytest.fixture(scope="module")
def ramp_nifti(tmp_path_factory: pytest.TempPathFactory) -> bytes:
    """A 40 x 36 x 30 CT-like ramp of many values (-1000 .. 1000 HU) with a bright cube."""
    i, j, k = np.mgrid[:40, :36, :30]
    values = (-1000 + i * 25 + j * 13 + k * 7).astype(np.int16)
    values[CUBE] = 1800
    affine = np.diag([-0.8, -0.8, 2.5, 1.0])  # RAS file: the server stores LPS
    affine[:3, 3] = [10.0, 20.0, -30.0]
    path = tmp_path_factory.mktemp("ramp") / "ramp.nii.gz"
    nib.save(nib.Nifti1Image(values, affine), path)
    return path.read_bytes()


@pytest.fixture(scope="module")
def ramp(client: TestClient, people: dict, ramp_nifti: bytes, upload_for) -> dict:
    return upload_for(client, people["alice"], ramp_nifti, "ramp.nii.gz")


def fetch(client: TestClient, volume_id: str, headers: dict, level: int = 0):
    return client.get(f"/api/volumes/{volume_id}/voxels?level={level}", headers=headers)


def test_the_owner_gets_the_stored_voxels_back_within_one_step(
    client: TestClient, people: dict, ramp: dict
) -> None:
    r = fetch(client, ramp["id"], people["alice"])
    assert r.status_code == 200, r.text
    assert r.headers["content-encoding"] == "gzip"
    header, sent = voxels.decode(r.content)  # httpx inflated it
    stored = client.app.state.store.open_volume(ramp["id"])
    assert header["dims"] == list(stored.data.shape) == [40, 36, 30]
    assert header["factors"] == [1, 1, 1] and header["units"] == "HU"
    np.testing.assert_allclose(header["affine"], stored.affine)
    real = sent * header["scale"] + header["offset"]
    lo, hi = header["offset"], header["offset"] + 255 * header["scale"]
    inside = (stored.data >= lo) & (stored.data <= hi)
    assert inside.mean() > 0.95  # the ends clip only the odd outlier
    error = np.abs(real - stored.data)[inside]
    assert error.max() <= header["scale"] / 2 + 1e-3
    assert (sent[stored.data > hi] == 255).all() and (sent[stored.data < lo] == 0).all()
    assert (sent[CUBE] == 255).all()  # the bright cube, at its voxels


def test_cacheable_for_good(client: TestClient, people: dict, ramp: dict) -> None:
    first = fetch(client, ramp["id"], people["alice"])
    cache = first.headers["cache-control"]
    assert "immutable" in cache and "private" in cache and "max-age=31536000" in cache
    again = fetch(client, ramp["id"], people["alice"] | {"If-None-Match": first.headers["etag"]})
    assert again.status_code == 304 and not again.content
    other = fetch(client, ramp["id"], people["alice"], level=1)
    assert other.status_code == 200 and other.headers["etag"] != first.headers["etag"]


def test_first_picture_within_six_tenths_of_int16(client: TestClient, demo_id: str) -> None:
    dims = client.get(f"/api/volumes/{demo_id}").json()["dims"]
    r = client.get(f"/api/volumes/{demo_id}/voxels")
    assert r.status_code == 200
    sent = int(r.headers["content-length"])  # the compressed bytes on the wire
    assert sent <= 0.6 * 2 * np.prod(dims), (sent, dims)


def test_without_gzip_the_body_comes_plain(client: TestClient, people: dict, ramp: dict) -> None:
    r = fetch(client, ramp["id"], people["alice"] | {"Accept-Encoding": "identity"})
    assert "content-encoding" not in r.headers
    header, sent = voxels.decode(r.content)
    assert sent.shape == (40, 36, 30)


def test_a_stranger_and_a_guest_get_404(
    client: TestClient, people: dict, ramp: dict, model_for
) -> None:
    assert fetch(client, ramp["id"], people["bob"]).status_code == 404
    model = model_for(client, people["alice"], ramp["id"], level=500)
    body = {"model": model["id"], "expires_in": 3600, "can_download": True}
    link = client.post("/api/shares", json=body, headers=people["alice"]).json()
    guest = TestClient(client.app)
    assert guest.get(link["url"] + "/info").status_code == 200  # the link works
    assert guest.get(link["url"] + "/voxels").status_code == 404
    assert guest.get(f"/api/volumes/{ramp['id']}/voxels").status_code in (401, 404)


def test_a_link_offers_the_scan_only_when_its_owner_allowed_it(
    client: TestClient, people: dict, ramp: dict, model_for
) -> None:
    """Issue 43: a link made with ``can_view_volume`` (a model link: its volume; a volume
    link: that volume) serves the guest the owner's bytes, never kept by a cache."""
    model = model_for(client, people["alice"], ramp["id"], level=500)
    mine = fetch(client, ramp["id"], people["alice"])
    guest = TestClient(client.app)
    for target in ({"model": model["id"]}, {"volume": ramp["id"]}):
        body = target | {"expires_in": 3600, "can_view_volume": True}
        r = client.post("/api/shares", json=body, headers=people["alice"])
        assert r.status_code == 201, r.text
        assert r.json()["can_view_volume"] is True
        got = guest.get(r.json()["url"] + "/voxels")
        assert got.status_code == 200, got.text
        assert got.content == mine.content
        assert got.headers["cache-control"] == "no-store"
        assert guest.get(r.json()["url"] + "/info").json()["share"]["can_view_volume"] is True
        client.delete(f"/api/shares/{r.json()['id']}", headers=people["alice"])
        assert guest.get(r.json()["url"] + "/voxels").status_code == 410  # revoked: gone


def test_a_scan_with_burned_in_text_waits_for_its_owner(
    client: TestClient, people: dict, datasets: Path, tmp_path: Path
) -> None:
    """A scan flagged for burned-in annotation (a real CT's slices, flagged as a scanner
    does) is offered to guests only once its owner confirms (409 with what to do until
    then); the surfaces may be shared meanwhile."""
    import io
    import zipfile

    import pydicom

    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as zf:
        for path in sorted((datasets / "ct_head_dicom_ge_gantrytilt").iterdir())[10:16]:
            ds = pydicom.dcmread(path)
            ds.BurnedInAnnotation = "YES"
            out = io.BytesIO()
            ds.save_as(out)
            zf.writestr(f"series/{path.name}", out.getvalue())
    files = {"file": ("flagged.zip", archive.getvalue(), "application/zip")}
    r = client.post("/api/volumes", files=files, headers=people["alice"])
    assert r.status_code == 201, r.text
    volume = r.json()
    assert volume["burned_in_annotation"]
    body = {"volume": volume["id"], "expires_in": 3600, "can_view_volume": True}
    r = client.post("/api/shares", json=body, headers=people["alice"])
    assert r.status_code == 409, r.text
    assert "burned into its pixels" in r.json()["detail"]
    assert "burned_in_confirmed" in r.json()["detail"]
    plain = {"volume": volume["id"], "expires_in": 3600}
    assert client.post("/api/shares", json=plain, headers=people["alice"]).status_code == 201
    r = client.post(
        "/api/shares", json=body | {"burned_in_confirmed": True}, headers=people["alice"]
    )
    assert r.status_code == 201, r.text
    assert TestClient(client.app).get(r.json()["url"] + "/voxels").status_code == 200


def test_links_from_before_the_volume_right_show_surfaces_only(tmp_path: Path) -> None:
    """Revision 0003 adds the column to a database at 0002, false for every old link."""
    from sqlalchemy import text

    from miss.server.core.settings import Settings
    from miss.server.storage.schema import head
    from miss.server.storage.store import Store

    url = Settings(data_dir=tmp_path).database_url
    store = Store(tmp_path, url)
    store.init()
    with store.engine.begin() as con:
        con.execute(text("ALTER TABLE shares DROP COLUMN can_view_volume"))
        con.execute(text("UPDATE alembic_version SET version_num = '0002'"))
    store.close()
    store = Store(tmp_path, url)
    store.init()
    try:
        with store.engine.connect() as con:
            columns = {row[1] for row in con.execute(text("PRAGMA table_info(shares)"))}
            version = con.execute(text("SELECT version_num FROM alembic_version")).scalar()
        assert "can_view_volume" in columns and version == head()
    finally:
        store.close()


def test_block_means_and_their_grid() -> None:
    """Level 0 shrinks a 600-wide axis by 3 (by the mean of each block) and places the
    block grid's voxel 0 at the centre of the first block."""
    data = np.arange(600 * 4 * 2, dtype=np.int16).reshape(600, 4, 2)
    f = voxels.factors(data.shape, 0, 2**30)
    assert f == (3, 1, 1)
    means = voxels.block_mean(data, f)
    assert means.shape == (200, 4, 2)
    np.testing.assert_allclose(means[5, 2, 1], data[15:18, 2, 1].mean())
    affine = np.diag([0.5, 0.7, 3.0, 1.0])
    affine[:3, 3] = [1, 2, 3]
    grid = voxels.grid_affine(affine, f)
    np.testing.assert_allclose(grid @ [0, 0, 0, 1], affine @ [1, 0, 0, 1])
    np.testing.assert_allclose(grid @ [2, 1, 1, 1], affine @ [7, 1, 1, 1])


def test_the_full_level_keeps_within_its_budget() -> None:
    assert voxels.factors((512, 512, 120), 1, 2**30) == (1, 1, 1)
    f = voxels.factors((512, 512, 120), 1, 8 * 2**20)
    assert np.prod([np.ceil(n / f[0]) for n in (512, 512, 120)]) <= 8 * 2**20
    assert f == (2, 2, 2)


def test_cthead_first_picture(datasets: Path) -> None:
    """CThead (256 x 256 x 113) goes whole at level 0, in under a quarter of its int16."""
    from miss.io import load_volume
    from miss.server.volumes import imaging

    scan = load_volume(datasets / "ct_head_stanford_cthead/CThead.nhdr")
    hist = imaging.histogram(scan.data)
    body = voxels.encode(scan.data, scan.affine, {}, hist, 0, 2**30)
    header, sent = voxels.decode(gzip.decompress(body))
    assert header["dims"] == [256, 256, 113]
    assert len(body) <= 0.25 * scan.data.size * 2
