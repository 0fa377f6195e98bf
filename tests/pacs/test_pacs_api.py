"""End to end against a real Orthanc: search, import, generate, send back, find it there."""

from __future__ import annotations

import json
import struct
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from support.server_app import ADMIN_PASSWORD, TestClient, bearer, log_in, wait_for_model

from miss.pacs.server import PacsServer
from miss.server.app import create_app
from miss.server.core.settings import Settings
from pacs.conftest import Series
from pacs.orthanc import Orthanc

GE = "ct_head_dicom_ge_gantrytilt"
ENCAPSULATED_STL = "1.2.840.10008.5.1.4.1.1.104.3"


def wait_import(client: TestClient, import_id: str, headers: dict[str, str]) -> dict[str, Any]:
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        body = client.get(f"/api/pacs/imports/{import_id}", headers=headers).json()
        if body["status"] in ("done", "failed"):
            return body
        time.sleep(0.2)
    raise AssertionError(f"import not finished: {body}")


def make_user(client: TestClient, name: str, pacs: bool) -> dict[str, str]:
    r = client.post("/api/users", json={"name": name, "password": f"{name}-password", "pacs": pacs})
    assert r.status_code == 201, r.text
    assert r.json()["pacs"] is pacs
    r = client.post(
        "/api/auth/login",
        json={"username": name, "password": f"{name}-password"},
        headers={"Authorization": ""},
    )
    client.cookies.clear()
    return bearer(r.json()["token"])


@pytest.fixture(scope="module")
def app(
    orthanc: Orthanc, pacs_series: dict[str, Series], tmp_path_factory: pytest.TempPathFactory
) -> Iterator[TestClient]:
    server = PacsServer("Orthanc", orthanc.dicomweb, orthanc.auth_file, timeout=20)
    data = tmp_path_factory.mktemp("pacs-api") / "data"
    settings = Settings(data_dir=data, admin_password=ADMIN_PASSWORD, demo=False, pacs=(server,))
    with TestClient(create_app(settings)) as c:
        log_in(c)
        yield c


@pytest.fixture(scope="module")
def radiologist(app: TestClient) -> dict[str, str]:
    return make_user(app, "rad", pacs=True)


def import_series(app: TestClient, headers: dict[str, str], series: Series) -> dict[str, Any]:
    body = {"study": series.study, "series": series.series}
    r = app.post("/api/pacs/import", json=body, headers=headers)
    assert r.status_code == 202, r.text
    assert r.headers["Location"] == f"/api/pacs/imports/{r.json()['id']}"
    return wait_import(app, r.json()["id"], headers)


def test_without_pacs_permission_every_route_is_404(app: TestClient) -> None:
    viewer = make_user(app, "viewer", pacs=False)
    calls = [
        ("GET", "/api/pacs", None),
        ("GET", "/api/pacs/studies?patient_id=MISS-PT-0001", None),
        ("GET", "/api/pacs/studies/1.2.3/series", None),
        ("POST", "/api/pacs/import", {"study": "1.2.3", "series": "1.2.4"}),
        ("GET", "/api/pacs/imports", None),
        ("GET", "/api/pacs/imports/abc", None),
        ("POST", "/api/models/abc/pacs", {}),
    ]
    for method, path, body in calls:
        r = app.request(method, path, json=body, headers=viewer)
        assert r.status_code == 404, (path, r.text)
        assert "detail" in r.json()


def test_search_import_generate_send_and_find_it_in_the_study(
    app: TestClient,
    radiologist: dict[str, str],
    pacs_series: dict[str, Series],
    orthanc: Orthanc,
    datasets: Path,
) -> None:
    ge = pacs_series[GE]
    # search by patient ID, then the study's series
    r = app.get("/api/pacs/studies", params={"patient_id": ge.patient_id}, headers=radiologist)
    assert r.status_code == 200, r.text
    studies = r.json()["studies"]
    assert [s["study"] for s in studies] == [ge.study]
    # (models other tests sent into the study count among its instances and series)
    assert studies[0]["patient_name"] == "DOE JANE" and studies[0]["instances"] >= ge.instances
    by_name = app.get("/api/pacs/studies", params={"patient_name": "doe"}, headers=radiologist)
    assert ge.study in [s["study"] for s in by_name.json()["studies"]]
    series = app.get(f"/api/pacs/studies/{ge.study}/series", headers=radiologist).json()
    listed = [(s["series"], s["modality"], s["importable"]) for s in series]
    assert (ge.series, "CT", True) in listed
    assert all(modality == "M3D" and not ok for uid, modality, ok in listed if uid != ge.series)
    # import: a volume without identity, the identity for its owner only
    done = import_series(app, radiologist, ge)
    assert done["status"] == "done", done
    volume = app.get(f"/api/volumes/{done['volume_id']}", headers=radiologist).json()
    shared = json.dumps(volume)
    for value in ("DOE", "JANE", ge.patient_id, ge.accession, "19610203", ge.study, ge.series):
        assert value not in shared, value
    from miss.io import load_volume

    read_here = load_volume(datasets / GE)  # the same reader as an upload's: same grid
    assert volume["dims"] == list(read_here.dims)
    assert volume["spacing"] == pytest.approx(list(read_here.spacing))
    identity = app.get(f"/api/volumes/{done['volume_id']}/identity", headers=radiologist)
    assert identity.status_code == 200 and ge.patient_id in identity.text
    # generate
    body = {"volume": done["volume_id"], "level": 300, "decimate": "quadric", "reduce": 0.9}
    r = app.post("/api/models", json=body, headers=radiologist)
    model = wait_for_model(app, r.json()["id"])
    assert model["status"] == "done", model
    # send back into the study
    r = app.post(f"/api/models/{model['id']}/pacs", json={}, headers=radiologist)
    assert r.status_code == 200, r.text
    sent = r.json()
    assert sent["description"].startswith("MISS surface: ") and "300 HU" in sent["description"]
    assert len(sent["sop_instance_uids"]) == 1
    # QIDO finds it in the original study; its STL is MISS's own, triangle for triangle
    from dicomweb_client import DICOMwebClient

    pacs = DICOMwebClient(orthanc.dicomweb)
    pacs._session.auth = (orthanc.user, orthanc.password)
    found = pacs.search_for_instances(
        study_instance_uid=ge.study, search_filters={"SOPClassUID": ENCAPSULATED_STL}
    )
    uids = [i["00080018"]["Value"][0] for i in found]
    assert set(sent["sop_instance_uids"]) <= set(uids)
    uids = sent["sop_instance_uids"]
    # the file as Orthanc stores it, read with pydicom
    import io

    import pydicom

    orthanc_id = orthanc.rest("POST", "/tools/lookup", data=uids[0]).json()[0]["ID"]
    raw = orthanc.rest("GET", f"/instances/{orthanc_id}/file").content
    ds = pydicom.dcmread(io.BytesIO(raw))  # a DICOM file: preamble, "DICM", meta
    assert ds.PatientID == ge.patient_id and ds.StudyInstanceUID == ge.study
    assert ds.FrameOfReferenceUID == ge.frame_of_reference
    assert ds.SeriesDescription == sent["description"] and ds.Modality == "M3D"
    assert ds.ReferencedSeriesSequence[0].SeriesInstanceUID == ge.series
    assert len(ds.SourceInstanceSequence) == ge.instances
    stl = bytes(ds.EncapsulatedDocument)[: ds.EncapsulatedDocumentLength]
    ours = app.get(f"/api/models/{model['id']}/model.stl", headers=radiologist)
    assert ours.status_code == 200, ours.text
    assert stl == ours.content
    (triangles,) = struct.unpack_from("<I", stl, 80)
    assert triangles == model["stats"]["triangles"] and len(stl) == 84 + 50 * triangles
    # the audit has each step, with no patient name or ID in it
    log = app.get("/api/audit").json()
    actions = {e["action"] for e in log}
    assert {"pacs_search", "pacs_import", "pacs_send"} <= actions
    assert ge.patient_id not in json.dumps(log) and "DOE" not in json.dumps(log)


def test_sent_instance_passes_dciodvfy(
    app: TestClient, radiologist: dict[str, str], pacs_series: dict[str, Series], tmp_path: Path
) -> None:
    """David Clunie's dciodvfy (Debian's dicom3tools) checks the instance against the
    Encapsulated STL IOD: no errors."""
    from miss.pacs.stl import Origin, encapsulate

    origin = Origin("1.2.3.4", "1.2.3.5", "1.2.3.6", {"PatientID": "X", "PatientName": "A^B"})
    ds = encapsulate([("bone", b"\0" * 84)], origin, "MISS surface: bone", "MISS test")[0]
    ds.StudyDate, ds.StudyTime, ds.StudyID = "20260101", "120000", "1"
    path = tmp_path / "stl.dcm"
    ds.save_as(path, enforce_file_format=True)
    out = subprocess.run(["dciodvfy", str(path)], capture_output=True, text=True, timeout=60)
    said = out.stdout + out.stderr
    assert "EncapsulatedSTL" in said, said
    assert "Error" not in said, said


def test_a_dicom_seg_beside_the_series_becomes_its_label_map(
    app: TestClient, radiologist: dict[str, str], pacs_series: dict[str, Series]
) -> None:
    """The abdomen CT (JPEG 2000 on the PACS, read as stored) comes with its
    TotalSegmentator SEG: the volume gets the 31 labels, named, and Generate makes one
    named, coloured part per segment."""
    abdomen = pacs_series["ct_abdomen_totalseg/dicom"]
    series = app.get(f"/api/pacs/studies/{abdomen.study}/series", headers=radiologist).json()
    kinds = {s["series"]: (s["modality"], s["importable"], s["segmentation"]) for s in series}
    assert kinds == {
        abdomen.series: ("CT", True, False),
        abdomen.segmentation: ("SEG", False, True),
    }
    done = import_series(app, radiologist, abdomen)
    assert done["status"] == "done", done
    assert done["labels"] == 31
    volume = app.get(f"/api/volumes/{done['volume_id']}", headers=radiologist).json()
    labelmap = volume["labelmap"]
    assert labelmap["table"] == "DICOM SEG" and len(labelmap["labels"]) == 31
    names = {e["name"] for e in labelmap["labels"]}
    assert {"liver", "spleen", "stomach"} <= names
    body = {"volume": done["volume_id"], "labels": "all", "decimate": "quadric"}
    r = app.post("/api/models", json=body, headers=radiologist)
    model = wait_for_model(app, r.json()["id"])
    assert model["status"] == "done", model
    parts = model["stats"]["parts"]
    assert {p["name"] for p in parts} <= names and "liver" in {p["name"] for p in parts}
    colors = {e["name"]: e["color"] for e in labelmap["labels"]}
    liver = next(p for p in parts if p["name"] == "liver")
    assert liver["color"] == pytest.approx(colors["liver"], abs=1e-3)
