"""A model is filed only where it belongs, and one account cannot hold up the PACS
imports of others (issue 39), against a real Orthanc.

- the attack: a DICOM zip whose StudyInstanceUID (and patient) were copied from another
  patient's study on the PACS is uploaded, modelled and sent: refused (409), and the
  study on the PACS gains nothing;
- a model of a PACS import goes back into its study, and only while the PACS still says
  that study has the patient and the series it was made from;
- with ``MISS_PACS_SEND_UPLOADS`` an upload's model goes as a new study, never into the
  study its file named;
- a UID with a trailing newline is not a UID; one account's flood of imports gets 429
  past its share and does not go ahead of another account's import.

Settings are given as environment (``Settings.from_env``) so that the tests run, and
fail, on code that predates them.
"""

from __future__ import annotations

import io
import os
import subprocess
import sys
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pydicom
import pytest
from pacs import conftest as pacs_fixtures
from pacs.conftest import Series, stow
from pacs.dicom_data import write_ct_series
from pacs.orthanc import Orthanc
from pacs.test_pacs_api import make_user, wait_import
from pydicom.uid import generate_uid
from support.server_app import ADMIN_PASSWORD, TestClient, log_in, make_model

from miss.pacs.server import PacsServer
from miss.server.app import create_app
from miss.server.core.settings import Settings

orthanc = pacs_fixtures.orthanc
pacs_series = pacs_fixtures.pacs_series
GE = "ct_head_dicom_ge_gantrytilt"
CAP = 4  # MISS_PACS_IMPORTS_PER_USER of the app here


def start_app(data: Path, orthanc: Orthanc, **env: str) -> TestClient:
    server = PacsServer("Orthanc", orthanc.dicomweb, orthanc.auth_file, timeout=20)
    settings = Settings.from_env(
        env, data_dir=data, admin_password=ADMIN_PASSWORD, demo=False, pacs=(server,)
    )
    client = TestClient(create_app(settings))
    client.__enter__()
    log_in(client)
    return client


@pytest.fixture(scope="module")
def app(orthanc: Orthanc, tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    data = tmp_path_factory.mktemp("pacs-safety") / "data"
    client = start_app(data, orthanc, MISS_PACS_IMPORTS="1", MISS_PACS_IMPORTS_PER_USER=str(CAP))
    yield client
    client.__exit__(None, None, None)


@pytest.fixture(scope="module")
def small(orthanc: Orthanc, tmp_path_factory: pytest.TempPathFactory) -> Series:
    """A 3-slice synthetic CT of a patient of its own, stored in the Orthanc."""
    paths = write_ct_series(tmp_path_factory.mktemp("small"), dims=(32, 28, 3))
    found = [pydicom.dcmread(p) for p in paths]
    for ds in found:
        ds.PatientName, ds.PatientID = "SAFE^SAM", "MISS-PT-0100"
    stow(orthanc, found)
    first = found[0]
    return Series(
        "small", "SAFE^SAM", "MISS-PT-0100", "", str(first.StudyInstanceUID),
        str(first.SeriesInstanceUID), str(first.FrameOfReferenceUID), len(found),
    )  # fmt: skip


def forged_zip(tmp_path: Path, victim: Series) -> bytes:
    """A small CT series whose files say they are of ``victim``'s study and patient (the
    UID and the patient's name and ID as a PACS search shows them), zipped."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for path in write_ct_series(tmp_path / "forged", dims=(32, 28, 6)):
            ds = pydicom.dcmread(path)
            ds.StudyInstanceUID = victim.study
            ds.PatientID, ds.PatientName = victim.patient_id, victim.patient_name
            buffer = io.BytesIO()
            ds.save_as(buffer, enforce_file_format=True)
            zf.writestr(f"series/{path.name}", buffer.getvalue())
    return out.getvalue()


def series_in(orthanc: Orthanc, study: str) -> set[str]:
    """The Series Instance UIDs Orthanc holds in ``study``."""
    found = orthanc.rest("POST", "/tools/lookup", data=study).json()
    if not found:
        return set()
    ids = orthanc.rest("GET", f"/studies/{found[0]['ID']}").json()["Series"]
    return {
        orthanc.rest("GET", f"/series/{i}").json()["MainDicomTags"]["SeriesInstanceUID"]
        for i in ids
    }


def upload_model(client: TestClient, headers: dict[str, str], content: bytes) -> dict[str, Any]:
    r = client.post("/api/volumes", files={"file": ("series.zip", content)}, headers=headers)
    assert r.status_code == 201, r.text
    return make_model(client, headers, r.json()["id"], level=-500)


def imported_model(client: TestClient, headers: dict[str, str], series: Series) -> dict[str, Any]:
    body = {"study": series.study, "series": series.series, "segmentation": "none"}
    r = client.post("/api/pacs/import", json=body, headers=headers)
    assert r.status_code == 202, r.text
    done = wait_import(client, r.json()["id"], headers)
    assert done["status"] == "done", done
    return make_model(client, headers, done["volume_id"], level=-500)


def audited(client: TestClient, action: str, model_id: str) -> list[dict[str, Any]]:
    return [
        e
        for e in client.get("/api/audit").json()
        if e["action"] == action and e["target"] == model_id
    ]


def test_an_upload_naming_another_patients_study_is_not_filed_there(
    app: TestClient, orthanc: Orthanc, pacs_series: dict[str, Series], tmp_path: Path
) -> None:
    """The attack of issue 39: refused with a reason, nothing stored, the refusal audited
    with the study it was aimed at."""
    victim = pacs_series[GE]
    rad = make_user(app, "mallory", pacs=True)
    model = upload_model(app, rad, forged_zip(tmp_path, victim))
    before = series_in(orthanc, victim.study)
    r = app.post(f"/api/models/{model['id']}/pacs", json={}, headers=rad)
    assert r.status_code == 409, r.text
    detail = r.json()["detail"]
    assert "uploaded" in detail and "Import the series from the PACS" in detail, detail
    assert victim.patient_id not in detail
    assert series_in(orthanc, victim.study) == before
    (refused,) = audited(app, "pacs_send_refused", model["id"])
    assert refused["detail"]["pacs"] == "Orthanc" and refused["actor"] == "mallory"
    assert not audited(app, "pacs_send", model["id"])


def test_an_import_goes_back_only_while_the_pacs_still_has_its_series(
    app: TestClient, orthanc: Orthanc, tmp_path: Path
) -> None:
    """The round trip still works (audited with the study it went to); once the source
    series is gone from the study (deleted, merged away) the send is refused."""
    paths = write_ct_series(tmp_path / "own", dims=(32, 28, 3))
    found = [pydicom.dcmread(p) for p in paths]
    for ds in found:
        ds.PatientName, ds.PatientID = "GONE^GIL", "MISS-PT-0101"
    stow(orthanc, found)
    own = Series("own", "GONE^GIL", "MISS-PT-0101", "", str(found[0].StudyInstanceUID),
                 str(found[0].SeriesInstanceUID), "", 3)  # fmt: skip
    rad = make_user(app, "rad-home", pacs=True)
    model = imported_model(app, rad, own)
    volume = app.get(f"/api/volumes/{model['volume']}", headers=rad).text
    assert own.patient_id not in volume and own.study not in volume  # the origin is owner-only
    r = app.post(f"/api/models/{model['id']}/pacs", json={}, headers=rad)
    assert r.status_code == 200, r.text
    assert r.json()["study_uid"] == own.study
    assert r.json()["series_uid"] in series_in(orthanc, own.study)
    (sent,) = audited(app, "pacs_send", model["id"])
    assert (
        sent["detail"]["study"] == own.study and sent["detail"]["series"] == r.json()["series_uid"]
    )
    # the source series is deleted on the PACS: the model no longer has a place there
    source = orthanc.rest("POST", "/tools/lookup", data=own.series).json()[0]["ID"]
    orthanc.rest("DELETE", f"/series/{source}")
    before = series_in(orthanc, own.study)
    r = app.post(f"/api/models/{model['id']}/pacs", json={}, headers=rad)
    assert r.status_code == 409, r.text
    assert "does not hold the series" in r.json()["detail"]
    assert series_in(orthanc, own.study) == before
    (refused,) = audited(app, "pacs_send_refused", model["id"])
    assert refused["detail"]["study"] == own.study


def test_an_import_is_not_sent_once_its_study_has_another_patient(
    app: TestClient, orthanc: Orthanc, tmp_path: Path
) -> None:
    """The PACS corrected the study's patient after the import (the same study, series
    and image UIDs, another patient ID): the model made before is refused."""
    paths = write_ct_series(tmp_path / "moved", dims=(32, 28, 3))
    found = [pydicom.dcmread(p) for p in paths]
    for ds in found:
        ds.PatientName, ds.PatientID = "MOVED^MAX", "MISS-PT-0102"
    stow(orthanc, found)
    study = str(found[0].StudyInstanceUID)
    moved = Series("moved", "MOVED^MAX", "MISS-PT-0102", "", study,
                   str(found[0].SeriesInstanceUID), "", 3)  # fmt: skip
    rad = make_user(app, "rad-moved", pacs=True)
    model = imported_model(app, rad, moved)
    # the PACS's correction: the same images (same UIDs) now of another patient
    orthanc_id = orthanc.rest("POST", "/tools/lookup", data=study).json()[0]["ID"]
    orthanc.rest("DELETE", f"/studies/{orthanc_id}")
    for ds in found:
        ds.PatientName, ds.PatientID = "OTHER^OLGA", "MISS-PT-0103"
    stow(orthanc, found)
    before = series_in(orthanc, study)
    r = app.post(f"/api/models/{model['id']}/pacs", json={}, headers=rad)
    assert r.status_code == 409, r.text
    detail = r.json()["detail"]
    assert "another patient ID" in detail and "MISS-PT-0103" not in detail, detail
    assert series_in(orthanc, study) == before


def test_uploads_go_as_a_new_study_only_when_allowed(
    orthanc: Orthanc, pacs_series: dict[str, Series], tmp_path: Path
) -> None:
    """MISS_PACS_SEND_UPLOADS=1: the forged upload's model is stored, in a study of its
    own with fresh UIDs; the study its file named gains nothing."""
    victim = pacs_series[GE]
    client = start_app(tmp_path / "data", orthanc, MISS_PACS_SEND_UPLOADS="1")
    try:
        rad = make_user(client, "rad", pacs=True)
        model = upload_model(client, rad, forged_zip(tmp_path, victim))
        before = series_in(orthanc, victim.study)
        r = client.post(f"/api/models/{model['id']}/pacs", json={}, headers=rad)
        assert r.status_code == 200, r.text
        study = r.json()["study_uid"]
        assert study != victim.study
        assert series_in(orthanc, victim.study) == before
        assert series_in(orthanc, study) == {r.json()["series_uid"]}
        (sent,) = audited(client, "pacs_send", model["id"])
        assert sent["detail"]["study"] == study
    finally:
        client.__exit__(None, None, None)


def test_a_uid_with_a_trailing_newline_is_refused(app: TestClient) -> None:
    """``$`` matches before a final newline; a UID is matched whole."""
    from miss.errors import BadParameter
    from miss.pacs import client

    study, series = "1.2.826.0.1.3680043.8.498.1", "1.2.826.0.1.3680043.8.498.2"
    with pytest.raises(BadParameter, match="not a DICOM UID"):
        client.check_uid(study + "\n", "study")
    rad = make_user(app, "rad-newline", pacs=True)
    for body in ({"study": study + "\n", "series": series},
                 {"study": study, "series": series + "\n"}):  # fmt: skip
        r = app.post("/api/pacs/import", json=body, headers=rad)
        assert r.status_code == 422, r.text
        assert "not a DICOM UID" in r.json()["detail"]
    assert app.get("/api/pacs/imports", headers=rad).json() == []
    r = app.get(f"/api/pacs/studies/{study}%0A/series", headers=rad)
    assert r.status_code == 422 and "not a DICOM UID" in r.json()["detail"], r.text


def test_one_account_has_its_share_of_imports_queued(app: TestClient, small: Series) -> None:
    """Past MISS_PACS_IMPORTS_PER_USER queued or running: 429 saying so; another account
    is still accepted."""
    flood = make_user(app, "flood", pacs=True)
    body = {"study": small.study, "series": small.series, "segmentation": "none"}
    answers = [app.post("/api/pacs/import", json=body, headers=flood) for _ in range(CAP + 3)]
    codes = [a.status_code for a in answers]
    assert codes[:CAP] == [202] * CAP and 429 in codes[CAP:], codes
    refused = next(a for a in answers if a.status_code == 429).json()["detail"]
    assert "MISS_PACS_IMPORTS_PER_USER" in refused and "GET /api/pacs/imports" in refused
    other = make_user(app, "other", pacs=True)
    r = app.post("/api/pacs/import", json=body, headers=other)
    assert r.status_code == 202, r.text
    for answer in [*answers, r]:
        if answer.status_code == 202:
            headers = other if answer is r else flood
            assert wait_import(app, answer.json()["id"], headers)["status"] == "done"


def test_a_flood_does_not_go_ahead_of_another_accounts_import(
    app: TestClient, small: Series
) -> None:
    """One import thread; one account queues its share, another then asks for one: the
    other's import is taken at the next turn, not after the whole flood (at most one of
    the flood's imports, the one already running, and one more had the PACS first)."""
    flood = make_user(app, "flood2", pacs=True)
    body = {"study": small.study, "series": small.series, "segmentation": "none"}
    queued = [app.post("/api/pacs/import", json=body, headers=flood) for _ in range(CAP)]
    assert [q.status_code for q in queued] == [202] * CAP
    other = make_user(app, "other2", pacs=True)
    mine = app.post("/api/pacs/import", json=body, headers=other)
    assert mine.status_code == 202, mine.text
    done = wait_import(app, mine.json()["id"], other)
    floods = [wait_import(app, q.json()["id"], flood) for q in queued]
    assert done["status"] == "done" and all(f["status"] == "done" for f in floods)
    ahead = [f for f in floods if f["finished_at"] < done["finished_at"]]
    assert len(ahead) <= 2, (len(ahead), CAP)


def test_a_flood_leaves_an_import_thread_free(
    orthanc: Orthanc, small: Series, tmp_path: Path
) -> None:
    """Two import threads; one account queues its share: its imports run one at a time
    (seen from its own list, polled as they go), so the other thread is free for the
    next account at once (the old pool ran two of the flood's at a time)."""
    client = start_app(tmp_path / "data", orthanc, MISS_PACS_IMPORTS="2")
    try:
        flood = make_user(client, "flood3", pacs=True)
        body = {"study": small.study, "series": small.series, "segmentation": "none"}
        queued = [client.post("/api/pacs/import", json=body, headers=flood) for _ in range(4)]
        assert [q.status_code for q in queued] == [202] * 4
        most = 0
        for _ in range(3000):
            rows = client.get("/api/pacs/imports", headers=flood).json()
            most = max(most, sum(r["status"] == "running" for r in rows))
            if all(r["status"] in ("done", "failed") for r in rows):
                break
            time.sleep(0.01)
        assert all(r["status"] == "done" for r in rows), rows
        assert most == 1, most
    finally:
        client.__exit__(None, None, None)


def test_a_busy_accounts_import_runs_behind_the_jobs(
    orthanc: Orthanc, small: Series, tmp_path: Path
) -> None:
    """Issue 39: a flood's imports (its account has more waiting) ran their retrieval,
    checks and writes on a server thread at nice 0, and their reads at nice 10, ahead of
    another account's job at nice 15. Now the whole import runs at READ_NICE (19) on a
    thread of its own; a single import of another account stays at the server's."""
    import threading

    from miss.server.pacs_exchange import READ_NICE

    client = start_app(tmp_path / "data", orthanc, MISS_PACS_IMPORTS="2")
    try:
        imports = client.app.state.pacs_imports
        seen: list[tuple[str, int]] = []
        run = imports._run

        def recorded(import_id: str, user: Any, server: Any, busy: bool) -> None:
            nice = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
            seen.append((user.name, nice))
            run(import_id, user, server, busy)

        imports._run = recorded
        flood = make_user(client, "flood4", pacs=True)
        body = {"study": small.study, "series": small.series, "segmentation": "none"}
        queued = [client.post("/api/pacs/import", json=body, headers=flood) for _ in range(4)]
        other = make_user(client, "other4", pacs=True)
        mine = client.post("/api/pacs/import", json=body, headers=other)
        assert wait_import(client, mine.json()["id"], other)["status"] == "done"
        for q in queued:
            assert wait_import(client, q.json()["id"], flood)["status"] == "done"
        base = os.getpriority(os.PRIO_PROCESS, 0)
        assert ("other4", base) in seen, seen
        assert ("flood4", min(19, base + READ_NICE)) in seen, seen
    finally:
        client.__exit__(None, None, None)


def test_the_command_line_checks_the_patient_before_storing(
    orthanc: Orthanc, pacs_series: dict[str, Series], tmp_path: Path
) -> None:
    """``miss pacs send --study`` of another patient's study (a copied UID): one line,
    exit 2, nothing stored; with the study's own patient ID it is stored."""
    ge = pacs_series[GE]
    stl = tmp_path / "model.stl"
    stl.write_bytes(b"\0" * 80 + (1).to_bytes(4, "little") + b"\0" * 50)
    env = {**os.environ, **orthanc.env("Orthanc")}
    before = series_in(orthanc, ge.study)
    args = [sys.executable, "-m", "miss.cli", "pacs", "send", str(stl), "--study", ge.study]
    out = subprocess.run([*args, "--patient-id", "MISS-PT-0002"], capture_output=True,
                         text=True, timeout=120, env=env)  # fmt: skip
    assert out.returncode == 2, out
    assert "another patient ID" in out.stderr and out.stderr.count("\n") == 1, out.stderr
    assert series_in(orthanc, ge.study) == before
    out = subprocess.run([*args, "--patient-id", ge.patient_id, "--series", generate_uid()],
                         capture_output=True, text=True, timeout=120, env=env)  # fmt: skip
    assert out.returncode == 2 and "does not hold the series" in out.stderr, out.stderr
    out = subprocess.run([*args, "--patient-id", ge.patient_id], capture_output=True,
                         text=True, timeout=120, env=env)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert len(series_in(orthanc, ge.study)) == len(before) + 1


def test_no_patient_id_is_served_with_the_volume(app: TestClient, small: Series) -> None:
    """The origin recorded at import (the PACS's patient ID, study and series) is in the
    owner-only identity record, not in what the volume's page or a guest gets."""
    rad = make_user(app, "rad-origin", pacs=True)
    body = {"study": small.study, "series": small.series, "segmentation": "none"}
    r = app.post("/api/pacs/import", json=body, headers=rad)
    done = wait_import(app, r.json()["id"], rad)
    served = app.get(f"/api/volumes/{done['volume_id']}", headers=rad).text
    for value in (small.patient_id, small.study, small.series, "SAFE"):
        assert value not in served, value
    identity = app.get(f"/api/volumes/{done['volume_id']}/identity", headers=rad).json()
    assert small.patient_id in str(identity)


@pytest.mark.parametrize(
    ("env", "said"),
    [
        ({"MISS_PACS_IMPORTS_PER_USER": "0"}, "MISS_PACS_IMPORTS_PER_USER must be at least 1"),
        ({"MISS_PACS_SEND_UPLOADS": "perhaps"}, "MISS_PACS_SEND_UPLOADS='perhaps' is not valid"),
    ],
)
def test_the_settings_say_what_is_wrong(env: dict[str, str], said: str) -> None:
    with pytest.raises(ValueError, match=said):
        Settings.from_env(env)
    assert Settings().pacs_send_uploads is False  # off unless the hospital allows it
