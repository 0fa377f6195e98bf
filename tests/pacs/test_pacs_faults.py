"""A PACS that is down, slow, refuses, or holds what MISS cannot model: clear answers,
nothing half-stored, and a retry that works once the PACS does."""

from __future__ import annotations

import io
import time
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pydicom
import pytest
from pydicom.uid import generate_uid
from support.server_app import ADMIN_PASSWORD, TestClient, log_in, wait_for_model

from miss.pacs.server import PacsServer
from miss.server.app import create_app
from miss.server.core.settings import Settings
from pacs import orthanc as orthanc_mod
from pacs.conftest import PATIENTS, Series, read_series, stow
from pacs.orthanc import Orthanc, free_port
from pacs.test_pacs_api import import_series, make_user, wait_import

GE = "ct_head_dicom_ge_gantrytilt"
MR = "mr_head_dicom_vsseg001_t1"


@pytest.fixture
def app_with(tmp_path: Path) -> Iterator[Callable[..., tuple[TestClient, dict[str, str]]]]:
    """``app_with(server, **settings)``: an app on a fresh folder whose user ``rad`` has
    PACS access: (client logged in as admin, rad's headers)."""
    clients: list[TestClient] = []

    def start(server: PacsServer, **overrides: Any) -> tuple[TestClient, dict[str, str]]:
        data = tmp_path / f"data{len(clients)}"
        settings = Settings(
            data_dir=data, admin_password=ADMIN_PASSWORD, demo=False, pacs=(server,), **overrides
        )
        client = TestClient(create_app(settings))
        client.__enter__()
        clients.append(client)
        log_in(client)
        return client, make_user(client, "rad", pacs=True)

    yield start
    for client in clients:
        client.__exit__(None, None, None)


def server_of(orthanc: Orthanc, timeout: float = 20) -> PacsServer:
    return PacsServer("Orthanc", orthanc.dicomweb, orthanc.auth_file, timeout)


def test_pacs_down_is_a_502_naming_it(app_with: Callable[..., Any]) -> None:
    gone = PacsServer("Archive", f"http://127.0.0.1:{free_port()}/dicom-web")
    client, rad = app_with(gone)
    r = client.get("/api/pacs/studies", params={"patient_id": "X"}, headers=rad)
    assert r.status_code == 502
    detail = r.json()["detail"]
    assert "cannot reach PACS 'Archive'" in detail and "connection refused" in detail
    assert "MISS_PACS_URL" in detail


def test_wrong_credentials_say_which_file_to_check(
    app_with: Callable[..., Any], orthanc: Orthanc, tmp_path: Path
) -> None:
    wrong = tmp_path / "auth"
    wrong.write_text(f"{orthanc.user}:not-the-password\n")
    client, rad = app_with(PacsServer("Orthanc", orthanc.dicomweb, wrong))
    r = client.get("/api/pacs/studies", params={"patient_id": "X"}, headers=rad)
    assert r.status_code == 502
    assert "refused MISS's credentials (401)" in r.json()["detail"]
    assert "not-the-password" not in r.text


def test_slow_pacs_times_out_and_the_import_can_be_retried(
    app_with: Callable[..., Any], orthanc: Orthanc, pacs_series: dict[str, Series]
) -> None:
    ge = pacs_series[GE]
    client, rad = app_with(server_of(orthanc, timeout=2))
    with orthanc.paused():
        r = client.get("/api/pacs/studies", params={"patient_id": ge.patient_id}, headers=rad)
        assert r.status_code == 504, r.text
        assert "did not answer within 2 s" in r.json()["detail"]
        started = client.post(
            "/api/pacs/import", json={"study": ge.study, "series": ge.series}, headers=rad
        )
        assert started.status_code == 202
        failed = wait_import(client, started.json()["id"], rad)
    assert failed["status"] == "failed" and "did not answer within 2 s" in failed["error"]
    assert client.get("/api/volumes", headers=rad).json() == []  # nothing half-stored
    again = import_series(client, rad, ge)
    assert again["status"] == "done", again


def test_a_report_series_is_not_importable_and_says_why(
    app_with: Callable[..., Any], orthanc: Orthanc
) -> None:
    sr = pydicom.Dataset()
    sr.SOPClassUID = "1.2.840.10008.5.1.4.1.1.88.11"  # Basic Text SR
    sr.SOPInstanceUID, sr.StudyInstanceUID, sr.SeriesInstanceUID = (generate_uid() for _ in "abc")
    sr.PatientID, sr.PatientName, sr.Modality = "MISS-PT-0004", "SR^ONLY", "SR"
    sr.file_meta = pydicom.dataset.FileMetaDataset()
    sr.file_meta.TransferSyntaxUID = pydicom.uid.ExplicitVRLittleEndian
    sr.file_meta.MediaStorageSOPClassUID, sr.file_meta.MediaStorageSOPInstanceUID = (
        sr.SOPClassUID, sr.SOPInstanceUID,
    )  # fmt: skip
    sr.preamble = b"\0" * 128
    stow(orthanc, [sr])
    client, rad = app_with(server_of(orthanc))
    listed = client.get(f"/api/pacs/studies/{sr.StudyInstanceUID}/series", headers=rad).json()
    assert [(s["importable"], s["reason"]) for s in listed] == [
        (False, "SR series: a structured report")
    ]
    body = {"study": sr.StudyInstanceUID, "series": sr.SeriesInstanceUID}
    r = client.post("/api/pacs/import", json=body, headers=rad)
    failed = wait_import(client, r.json()["id"], rad)
    assert failed["status"] == "failed"
    assert "holds no images" in failed["error"] and "pick an image series" in failed["error"]


def test_a_series_over_the_upload_limit_is_refused(
    app_with: Callable[..., Any], orthanc: Orthanc, pacs_series: dict[str, Series]
) -> None:
    mr = pacs_series[MR]  # 62 MB
    client, rad = app_with(server_of(orthanc), max_upload_mb=8)
    failed = import_series(client, rad, mr)
    assert failed["status"] == "failed"
    assert "more than 8 MB" in failed["error"] and "MISS_MAX_UPLOAD_MB" in failed["error"]
    assert client.get("/api/volumes", headers=rad).json() == []


def _halved(ds: pydicom.Dataset) -> pydicom.Dataset:
    """One slice at half the resolution (every other pixel): a series of mixed sizes."""
    pixels = ds.pixel_array[::2, ::2].copy()
    ds.Rows, ds.Columns = pixels.shape
    ds.PixelSpacing = [float(v) * 2 for v in ds.PixelSpacing]
    ds.PixelData = pixels.astype(np.int16 if ds.PixelRepresentation else np.uint16).tobytes()
    return ds


@pytest.mark.parametrize("fault", ["mixed sizes", "missing slices"])
def test_broken_series_get_the_same_answer_as_an_upload(
    fault: str, app_with: Callable[..., Any], orthanc: Orthanc, datasets: Path
) -> None:
    """A series with slices of two sizes, or with a gap of missing slices: the import's
    answer is the upload's answer for the same files (both refused with the same message,
    or both read to the same grid)."""
    patient = ("GAP^" + fault.split()[0].upper(), f"MISS-{fault[:3]}", "19800101", "ACC9")
    found = read_series(datasets / MR, patient)
    found.sort(key=lambda ds: float(ds.ImagePositionPatient[2]))
    study, series = generate_uid(), generate_uid()
    for ds in found:
        ds.StudyInstanceUID, ds.SeriesInstanceUID = study, series
    if fault == "mixed sizes":
        found[5] = _halved(found[5])
    else:
        del found[50:56]
    stow(orthanc, found)
    client, rad = app_with(server_of(orthanc))
    imported = import_series(client, rad, Series("", "", "", "", study, series, "", len(found)))
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as zf:
        for i, ds in enumerate(found):
            buffer = io.BytesIO()
            ds.save_as(buffer, enforce_file_format=True)
            zf.writestr(f"series/{i:04d}.dcm", buffer.getvalue())
    uploaded = client.post(
        "/api/volumes", files={"file": ("series.zip", archive.getvalue())}, headers=rad
    )
    if uploaded.status_code == 201:
        assert imported["status"] == "done", imported
        volume = client.get(f"/api/volumes/{imported['volume_id']}", headers=rad).json()
        assert volume["dims"] == uploaded.json()["dims"]
        assert volume["notes"] == uploaded.json()["notes"] and volume["notes"]  # said alike
    else:
        assert imported["status"] == "failed"
        assert imported["error"] == uploaded.json()["detail"]


REFUSALS = {
    # Orthanc drops the instance but its DICOMweb plugin answers "stored": MISS checks
    "filtered": (
        "function ReceivedInstanceFilter(dicom, origin, info)\n"
        "  return dicom.Modality ~= 'M3D'\nend\n",
        "holds 0 of the 1 instance(s) it was sent",
    ),
    # Orthanc refuses the request itself (but for the tests' own setup, which says so)
    "forbidden": (
        "function IncomingHttpRequestFilter(method, uri, ip, username, headers)\n"
        "  return headers['x-miss-test-setup'] ~= nil or\n"
        "    not (method == 'POST' and string.find(uri, '/dicom-web/', 1, true) == 1)\nend\n",
        "refused (403 forbidden) while storing the model",
    ),
}


@pytest.mark.parametrize("refusal", sorted(REFUSALS))
def test_a_refused_store_shows_the_pacs_reason(
    refusal: str, app_with: Callable[..., Any], datasets: Path, tmp_path: Path
) -> None:
    """An Orthanc that will not keep 3-D models: the send is a 502 that says what the PACS
    did, the study is as it was, and no send is audited."""
    lua, said = REFUSALS[refusal]
    refusing = orthanc_mod.start(tmp_path / "refusing", lua=lua)
    try:
        found = read_series(datasets / GE, PATIENTS[GE])
        stow(refusing, found)
        ge = Series(GE, "", "", "", str(found[0].StudyInstanceUID),
                    str(found[0].SeriesInstanceUID), "", len(found))  # fmt: skip
        client, rad = app_with(server_of(refusing))
        done = import_series(client, rad, ge)
        body = {"volume": done["volume_id"], "level": 300, "sample_rate": 4}
        model = wait_for_model(
            client, client.post("/api/models", json=body, headers=rad).json()["id"]
        )
        assert model["status"] == "done", model
        before = refusing.rest("GET", "/instances").json()
        r = client.post(f"/api/models/{model['id']}/pacs", json={}, headers=rad)
        assert r.status_code == 502, r.text
        assert "PACS 'Orthanc'" in r.json()["detail"] and said in r.json()["detail"]
        assert refusing.rest("GET", "/instances").json() == before
        assert "pacs_send" not in {e["action"] for e in client.get("/api/audit").json()}
    finally:
        refusing.stop()


def test_the_permission_is_granted_and_taken_back(
    app_with: Callable[..., Any], orthanc: Orthanc
) -> None:
    client, rad = app_with(server_of(orthanc))
    assert client.get("/api/pacs", headers=rad).status_code == 200
    r = client.patch("/api/users/rad", json={"pacs": False})
    assert r.status_code == 200 and r.json()["pacs"] is False
    assert client.get("/api/pacs", headers=rad).status_code == 404
    time.sleep(0)  # the login goes on: only the permission changed
    assert client.get("/api/auth/me", headers=rad).json()["pacs"] is False


def test_an_import_under_way_when_the_server_stopped_fails_with_the_reason(
    tmp_path: Path,
) -> None:
    """A server killed mid-import: at the next start the import says what happened (and
    the owner imports again); nothing stays 'running' for ever."""
    from miss.server.pacs_exchange import RESTARTED
    from miss.server.storage.db import PacsImportRow, UserRow
    from miss.server.storage.store import Store

    data = tmp_path / "data"
    store = Store(data, Settings(data_dir=data).database_url)
    store.init()
    with store.session.begin() as s:
        s.add(UserRow(id="u1", name="rad", password="x", pacs=True))
        s.flush()
        s.add(PacsImportRow(id="i1", owner_id="u1", pacs="P", study="1.2", series="1.3",
                            status="running"))  # fmt: skip
    store.close()
    settings = Settings(data_dir=data, admin_password=ADMIN_PASSWORD, demo=False)
    with TestClient(create_app(settings)):
        pass
    store = Store(data, settings.database_url)
    with store.session() as s:
        row = s.get(PacsImportRow, "i1")
    store.close()
    assert (row.status, row.error) == ("failed", RESTARTED)
