"""A DICOM SEG / RT-STRUCT laid over a stored volume (what the PACS import will do):
read confined, stored as the volume's label map, then "Generate" with labels "all"
makes one part per segment, named and coloured after it."""

from __future__ import annotations

import io
import shutil
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from pacs.dicom_data import write_ct_series, write_rtstruct, write_small_seg

from miss.errors import BadParameter
from miss.server.volumes import labelmaps


def _zip(folder: Path) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:
        for path in sorted(folder.iterdir()):
            z.write(path, path.name)
    return buffer.getvalue()


def _work(client: TestClient, name: str) -> Path:
    work = client.app.state.store.data_dir / "tmp" / name  # type: ignore[attr-defined]
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    return work


@pytest.mark.slow
def test_segmentations_become_named_coloured_parts(
    client: TestClient,
    people: dict[str, dict[str, str]],
    upload_for: Callable[..., dict[str, Any]],
    wait_done: Callable[..., dict[str, Any]],
    tmp_path: Path,
) -> None:
    alice = people["alice"]
    write_ct_series(tmp_path / "ct")
    write_rtstruct(tmp_path / "ct", tmp_path / "rt")
    vid = upload_for(client, alice, _zip(tmp_path / "ct"), "phantom.zip")["id"]
    store = client.app.state.store  # type: ignore[attr-defined]
    reading = client.app.state.reading  # type: ignore[attr-defined]
    scan = store.open_volume(vid)  # de-identified UIDs, the original geometry

    # RT-STRUCT among the series' files, as a PACS retrieve leaves them
    work = _work(client, "rt")
    shutil.copytree(tmp_path / "ct", work / "unzipped")
    shutil.copy(tmp_path / "rt" / "rtstruct.dcm", work / "unzipped")
    labels, meta = labelmaps.read_segmentation(work / "unzipped", scan, work, reading)
    assert meta["table"] == "RT-STRUCT"
    assert [e["name"] for e in meta["labels"]] == ["box", "cylinder", "tube"]
    labelmaps.save(store, vid, labels, meta)
    public = client.get(f"/api/volumes/{vid}", headers=alice).json()["labelmap"]
    assert public["table"] == "RT-STRUCT" and len(public["labels"]) == 3

    body = {"volume": vid, "labels": "all", "sample_rate": 1, "decimate": "none"}
    r = client.post("/api/models", json=body, headers=alice)
    assert r.status_code == 202, r.text
    model = wait_done(client, r.json()["id"])
    assert model["status"] == "done", model
    parts = {p["name"]: p for p in model["stats"]["parts"]}
    assert sorted(parts) == ["box", "cylinder", "tube"]
    assert parts["box"]["color"] == pytest.approx([220 / 255, 40 / 255, 40 / 255], abs=1e-4)

    # a SEG file on its own replaces it; its names and colours reach the parts
    mask = np.zeros(scan.dims, bool)
    mask[10:30, 10:30, 2:8] = True
    colors = {"lesion": (1.0, 0.5, 0.0)}
    seg = write_small_seg(tmp_path / "ct", tmp_path / "seg", {"lesion": mask}, colors=colors)
    work = _work(client, "seg")
    shutil.copy(seg, work / "seg.dcm")
    labels, meta = labelmaps.read_segmentation(work / "seg.dcm", scan, work, reading)
    assert meta["table"] == "DICOM SEG" and meta["labels"][0]["voxels"] == mask.sum()
    labelmaps.save(store, vid, labels, meta)
    model = wait_done(client, client.post("/api/models", json=body, headers=alice).json()["id"])
    (part,) = model["stats"]["parts"]
    assert part["name"] == "lesion"
    assert part["color"] == pytest.approx([1.0, 0.5, 0.0], abs=1.01 / 255)

    # a segmentation of another place in patient space does not overlap the volume
    far = tmp_path / "far"
    write_ct_series(far, origin=(500.0, 500.0, 500.0))
    seg = write_small_seg(far, tmp_path / "farseg", {"x": np.ones((64, 56, 12), bool)})
    work = _work(client, "far")
    shutil.copy(seg, work / "seg.dcm")
    with pytest.raises(BadParameter, match="does not overlap"):
        labelmaps.read_segmentation(work / "seg.dcm", scan, work, reading)
