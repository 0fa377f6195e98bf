"""A volume's suggested levels fit its modality: CT keeps bone and skin in its own units,
MR (and a file without a modality whose values are not CT's) gets skin and tissue from
its histogram, never "bone", and the level's field is named for what it measures.
The real scans in ../shared/datasets decide."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from miss.io import load_volume
from miss.pipeline import run
from miss.server.volumes import imaging
from miss.spec import JobSpec
from miss.types import Mesh, Volume

MR_HEAD = "mr_head_dicom_vsseg001_t1"


def described(volume: Volume) -> tuple[dict[str, str], dict[str, float]]:
    """The volume's scale and its presets, {name: level}, the default first."""
    hist = imaging.histogram(np.asarray(volume.data))
    units, modality = volume.meta.get("units", ""), volume.meta.get("modality", "")
    presets = imaging.presets(hist, units, modality)
    return imaging.scale(hist, modality, units), {p["name"]: p["level"] for p in presets}


@pytest.fixture(scope="module")
def mr_head(datasets: Path) -> Volume:
    return load_volume(datasets / MR_HEAD)


def largest_share(mesh: Mesh) -> float:
    """The share of the triangles in the mesh's largest connected piece."""
    faces = np.asarray(mesh.faces)
    n = len(mesh.vertices)
    ends = (np.concatenate([faces[:, 0], faces[:, 1]]), np.concatenate([faces[:, 1], faces[:, 2]]))
    graph = coo_matrix((np.ones(len(ends[0])), ends), shape=(n, n))
    count, labels = connected_components(graph, directed=False)
    per_piece = np.bincount(labels[faces[:, 0]], minlength=count)
    return float(per_piece.max() / per_piece.sum())


def test_an_mr_head_opens_on_its_skin_never_on_bone(mr_head: Volume) -> None:
    scale, presets = described(mr_head)
    assert scale["label"] == "Intensity" and scale["kind"] == "MR"
    assert "bone" not in presets
    default, level = next(iter(presets.items()))
    assert default == "skin" and 230 < level < 320  # the background/head split (about 270)
    assert presets["tissue"] > level


def test_the_default_level_makes_a_head_not_speckle(mr_head: Volume) -> None:
    """The old default (the 95th percentile called "bone", 738) scattered its triangles
    over thousands of pieces (26 % in the largest); the skin is one surface."""
    _, presets = described(mr_head)
    default = next(iter(presets.values()))
    spec = JobSpec.of(level=default, sample_rate=2, formats=("glb",), decimate="none")
    assert largest_share(run(mr_head, spec, measure=False).mesh) > 0.85
    old = JobSpec.of(level=738.0, sample_rate=2, formats=("glb",), decimate="none")
    assert largest_share(run(mr_head, old, measure=False).mesh) < 0.5  # what the test tells


@pytest.mark.parametrize(
    ("path", "kind"),
    [
        ("nifti/MR_Gd.nii.gz", "MR"),  # skull-stripped, no modality in NIfTI
        ("mr_forearm_dicom_cptac_sar", "MR"),
        # a raw CT as the scanner stored it (HU + 1024), no header modality: soft tissue's peak
        ("ct_head_stanford_cthead/CThead.nhdr", "CT"),
        # VTK's "headsq" is named MR here but its values are a CT's (bone bright, soft tissue at
        # 1080): it keeps bone
        ("mr_headsq_quarter/quarter.nhdr", "CT"),
    ],
)
def test_a_file_without_a_modality_is_decided_from_its_histogram(
    datasets: Path, path: str, kind: str
) -> None:
    scale, presets = described(load_volume(datasets / path))
    assert scale["kind"] == kind, scale
    assert scale["reason"]
    if kind == "MR":
        assert list(presets) == ["skin", "tissue"] and scale["label"] == "Intensity"
    else:
        assert list(presets) == ["bone", "skin"] and scale["label"].startswith("Density")


def test_ct_in_hounsfield_units_keeps_its_presets(datasets: Path) -> None:
    scale, presets = described(load_volume(datasets / "ct_head_dicom_ge_gantrytilt"))
    assert scale["label"] == "Density (HU)"
    assert presets == {"bone": 300.0, "skin": -500.0}


def test_the_api_names_the_scale_and_lists_the_default_first(
    client: TestClient, datasets: Path
) -> None:
    path = datasets / "nifti" / "MR_Gd.nii.gz"
    r = client.post("/api/volumes", files={"file": (path.name, path.read_bytes())})
    assert r.status_code == 201, r.text
    body: dict[str, Any] = r.json()
    assert body["scale"]["label"] == "Intensity"
    assert "no modality" in body["scale"]["reason"]
    assert [p["name"] for p in body["presets"]] == ["skin", "tissue"]
    hist = client.get(f"/api/volumes/{body['id']}/histogram").json()
    assert hist["presets"][0]["name"] == "skin"
