"""A data folder of a MISS before Zarr (``data.npy``, ``labels.npy``) is migrated when the
server starts: the same voxels, served the same, and a migration cut short is redone."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient
from support import ADMIN_PASSWORD
from support.pg import copy_seed
from support.server_app import started as start_logged_in

from miss.server.storage import chunked
from miss.server.volumes import labelmaps
from miss.structures.labelmap import label_counts
from miss.types import Volume

BIG = 1 << 40


def started(data: Path) -> TestClient:
    return start_logged_in(data, ADMIN_PASSWORD)


def make_old(folder: Path) -> tuple[np.ndarray, np.ndarray]:
    """Store ``folder``'s volume as MISS did before Zarr, with a label map; leave what a
    migration cut short would: a staging folder, a finished Zarr copy beside the .npy
    (here a wrong one, so that keeping it would show). Returns (voxels, labels)."""
    voxels = np.asfortranarray(chunked.read(folder / "data.zarr", BIG))
    np.save(folder / "data.npy", voxels, allow_pickle=False)
    shutil.rmtree(folder / "data.zarr")
    affine = np.array(json.loads((folder / "meta.json").read_text())["affine"])
    labels = np.asfortranarray((voxels > 300).astype(np.uint8) + (voxels > 1000))
    np.save(folder / "labels.npy", labels, allow_pickle=False)
    mask = Volume(labels, affine)
    meta = labelmaps._meta(mask, label_counts(mask) or {}, {}, "test")
    (folder / "labels.json").write_text(json.dumps(meta))
    chunked.write_array(folder / "labels.zarr", np.zeros_like(labels), {"affine": affine})
    (folder / ".data.zarr.0badc0de.part").mkdir()
    (folder / ".data.zarr.0badc0de.part" / "zarr.json").write_text("{")
    return voxels, labels


def test_old_data_folder_is_migrated_at_start_and_served_the_same(
    seeded_dir: Path, tmp_path: Path
) -> None:
    new = copy_seed(seeded_dir, tmp_path / "new")
    client = started(new)
    try:
        (demo,) = (v["id"] for v in client.get("/api/volumes").json())
        want = client.get(f"/api/volumes/{demo}/slices/coronal/40.png").content
    finally:
        client.__exit__(None, None, None)
    old = copy_seed(seeded_dir, tmp_path / "old")
    folder = old / "volumes" / demo
    voxels, labels = make_old(folder)

    client = started(old)
    try:
        assert sorted(p.name for p in folder.iterdir()) == [
            "data.zarr",
            "histogram.json",
            "labels.json",
            "labels.zarr",
            "meta.json",
            "thumbnail.png",
        ]
        assert np.array_equal(chunked.read(folder / "data.zarr", BIG), voxels)
        assert np.array_equal(chunked.read(folder / "labels.zarr", BIG), labels)
        r = client.get(f"/api/volumes/{demo}/slices/coronal/40.png")
        assert r.status_code == 200 and r.content == want
        shown = client.get(f"/api/volumes/{demo}").json()["labelmap"]["labels"]
        assert [e["label"] for e in shown] == [1, 2]
    finally:
        client.__exit__(None, None, None)
    again = started(old)  # nothing left to migrate: starts as usual
    again.__exit__(None, None, None)
    assert not list(folder.glob("*.npy"))


def test_a_zarr_copy_that_differs_keeps_the_npy(
    seeded_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Verification is real: a copy that reads back different leaves the .npy in place."""
    from miss.server.storage import store

    old = copy_seed(seeded_dir, tmp_path / "old")
    (folder,) = (old / "volumes").iterdir()
    make_old(folder)
    monkeypatch.setattr(store.chunked, "same_voxels", lambda path, data: False)
    with pytest.raises(RuntimeError, match="differs from it; data.npy is kept"):
        started(old)
    assert (folder / "data.npy").exists() and not (folder / "data.zarr").exists()
