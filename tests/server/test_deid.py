"""De-identification: a DICOM series full of identity goes in; no response, stored file,
database table (but the owner's identity record), log line or exported model carries any
of it out. UIDs are remapped consistently; the burned-in annotation flag is reported."""

from __future__ import annotations

import gzip
import logging
import sqlite3
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pydicom
import pytest
from fastapi.testclient import TestClient

IDENTITY = {
    "PatientName": "Zebedee^Quixote^Marmaduke",
    "PatientID": "PID-7731-QX",
    "PatientBirthDate": "19230417",
    "PatientAddress": "42 Wallaby Way, Sydney",
    "PatientTelephoneNumbers": "+61-2-5550-1234",
    "OtherPatientIDs": "OTHER-ID-5521",
    "InstitutionName": "Saint Ignatius Hospital of Nowhere",
    "InstitutionAddress": "7 Lantern Road, Nowhere",
    "AccessionNumber": "ACC99812Z",
    "ReferringPhysicianName": "Feelgood^Hippocrates",
    "OperatorsName": "Tecnica^Rosalind",
}
PRIVATE_VALUE = "PRIVATE-SECRET-7788"
#: The person names' parts, which may appear spelled another way ("Quixote Zebedee").
NAME_PARTS = ["Zebedee", "Quixote", "Marmaduke", "Feelgood", "Hippocrates", "Tecnica", "Rosalind"]
SLICES = 8
WAITING = ("queued", "running")


@pytest.fixture(scope="module")
def identified_zip(datasets: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, set]:
    """Eight slices of a real head CT rewritten with identity everywhere (and a private
    tag, a burned-in annotation flag, a description naming the patient), zipped in a
    folder and a file named after the patient. Returns (zip, original UIDs)."""
    folder = tmp_path_factory.mktemp("phi") / "ZEBEDEE_QUIXOTE_PID-7731-QX"
    folder.mkdir()
    uids: set[str] = set()
    source = sorted((datasets / "ct_head_dicom_ge_gantrytilt").iterdir())[10 : 10 + SLICES]
    for n, path in enumerate(source):
        ds = pydicom.dcmread(path)
        for keyword, value in IDENTITY.items():
            setattr(ds, keyword, value)
        ds.SeriesDescription = "Head for Zebedee"
        ds.BurnedInAnnotation = "YES"
        ds.private_block(0x0011, "MISS TEST", create=True).add_new(0x01, "LO", PRIVATE_VALUE)
        for keyword in ("SeriesInstanceUID", "StudyInstanceUID", "SOPInstanceUID"):
            uids.add(str(ds.get(keyword, "")))
        uids.add(str(ds.get("FrameOfReferenceUID", "")))
        ds.save_as(folder / f"IM{n:04d}.dcm")
    archive = folder.parent / "Zebedee_Quixote.zip"
    with zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as zf:
        for f in sorted(folder.iterdir()):
            zf.write(f, f"{folder.name}/{f.name}")
    return archive, {u for u in uids if u}


def secrets_in(uids: set[str]) -> list[str]:
    values = [*IDENTITY.values(), PRIVATE_VALUE, *NAME_PARTS, *uids]
    values += [v.replace("^", " ") for v in IDENTITY.values()]
    return [v.lower() for v in values]


def leaks(data: bytes, secrets: list[str]) -> list[str]:
    lower = data.lower()
    return [s for s in secrets if s.encode() in lower]


class Recorder:
    """Every response the test provokes, to grep them all afterwards."""

    def __init__(self, client: TestClient) -> None:
        self.client, self.seen = client, []

    def __call__(self, method: str, url: str, **kwargs: Any) -> Any:
        r = self.client.request(method, url, **kwargs)
        assert r.status_code < 400, (url, r.status_code, r.text)
        body = gzip.decompress(r.content) if url.endswith(".wrz") else r.content
        self.seen.append((url, body + str(dict(r.headers)).encode()))
        return r


@pytest.fixture
def all_logs(caplog: pytest.LogCaptureFixture) -> Iterator[pytest.LogCaptureFixture]:
    with caplog.at_level(logging.DEBUG):
        yield caplog


def visit_everything(call: Recorder, client: TestClient, alice: dict, zip_path: Path) -> dict:
    """Upload, look, make a model, download it all, share, consult: what a user does."""
    volume = call(
        "POST",
        "/api/volumes",
        files={"file": (zip_path.name, zip_path.read_bytes())},
        headers=alice,
    ).json()
    vid = volume["id"]
    for url in (
        "",
        "/histogram",
        "/thumbnail.png",
        "/slices/axial/3.png",
        "/slices/sagittal/9.png",
    ):
        call("GET", f"/api/volumes/{vid}{url}", headers=alice)
    call("GET", "/api/volumes", headers=alice)
    call("GET", f"/volumes/{vid}", headers=alice)
    return {"volume": volume, "model": model_share_consult(call, client, alice, vid)}


def model_share_consult(call: Recorder, client: TestClient, alice: dict, vid: str) -> dict:
    """Make a model, download every format, share it, talk about it in its room."""
    body = {"volume": vid, "level": 300, "sample_rate": 2, "decimate": "quadric"}
    model_id = call("POST", "/api/models", json=body, headers=alice).json()["id"]
    deadline = time.monotonic() + 120
    while client.get(f"/api/models/{model_id}", headers=alice).json()["status"] in WAITING:
        assert time.monotonic() < deadline, "the model took too long"
        time.sleep(0.2)
    model = call("GET", f"/api/models/{model_id}", headers=alice).json()
    assert model["status"] == "done", model
    call("GET", f"/models/{model_id}", headers=alice)
    for fmt in model["files"]:
        call("GET", f"/api/models/{model_id}/model.{fmt}", headers=alice)
    link = call(
        "POST",
        "/api/shares",
        json={"model": model_id, "can_download": True, "can_annotate": True},
        headers=alice,
    ).json()
    for suffix in ("", "/info", "/model.glb", "/model.obj"):
        call("GET", link["url"] + suffix)
    with client.websocket_connect(f"/ws/rooms/{model_id}?share={link['url'][3:]}&name=Guest") as ws:
        call.seen.append(("ws welcome", ws.receive_text().encode()))
        ws.send_json({"type": "chat", "text": "looks fine"})
        call.seen.append(("ws chat", ws.receive_text().encode()))
    for url in ("/room/events", "/room/sessions", "/events"):
        call("GET", f"/api/models/{model_id}{url}", headers=alice)
    call("GET", "/api/shares", headers=alice)
    call("GET", "/api/audit")
    return model


def test_no_identity_leaves_the_server(
    client: TestClient, people: dict, identified_zip: tuple[Path, set], all_logs
) -> None:
    zip_path, uids = identified_zip
    alice = people["alice"]
    call = Recorder(client)
    made = visit_everything(call, client, alice, zip_path)
    secrets = secrets_in(uids)
    for url, body in call.seen:
        assert not leaks(body, secrets), f"{url} leaks {leaks(body, secrets)}"
    data = Path(client.app.state.settings.data_dir)
    for path in data.rglob("*"):
        if path.is_file() and not path.name.startswith("miss.sqlite3"):
            content = path.read_bytes()
            content = gzip.decompress(content) if path.suffix == ".wrz" else content
            assert not leaks(content, secrets), f"{path} leaks {leaks(content, secrets)}"
    assert not leaks("\n".join(r.getMessage() for r in all_logs.records).encode(), secrets)
    check_database(data / "miss.sqlite3", secrets, made["volume"]["id"])
    # What the volume says about itself: names only, remapped UIDs, the burned-in flag.
    volume = made["volume"]
    # Never named after its file (named after the patient): by modality, body part and,
    # the description having had a name cut out, the upload's time.
    assert volume["name"].startswith("CT HEAD volume, uploaded ")
    assert volume["burned_in_annotation"]
    assert set(IDENTITY) <= set(volume["deidentification"]["removed"])
    assert volume["deidentification"]["private_tags_dropped"] >= 1
    assert volume["series"][0]["uid"].startswith("2.25.")
    assert volume["series"][0]["description"] == "Head for [removed]"


def check_database(db: Path, secrets: list[str], volume_id: str) -> None:
    """Every table but ``identities`` is clean; that one holds the owner's record."""
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as conn:
        tables = [r[0] for r in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")]
        for table in tables:
            rows = repr(conn.execute(f"SELECT * FROM {table}").fetchall()).encode()
            if table == "identities":
                assert IDENTITY["PatientName"].encode() in rows and volume_id.encode() in rows
            else:
                assert not leaks(rows, secrets), f"table {table} leaks {leaks(rows, secrets)}"
    assert "identities" in tables


@pytest.mark.slow  # two real DICOM series uploaded
def test_identity_record_is_the_owners_alone(
    client: TestClient, people: dict, identified_zip: tuple[Path, set]
) -> None:
    zip_path, uids = identified_zip
    files = {"file": (zip_path.name, zip_path.read_bytes())}
    first = client.post("/api/volumes", files=files, headers=people["alice"]).json()
    # The series named by the UID the API showed (the remapped one) is found in the files.
    chosen = {"series": first["series"][0]["uid"]}
    again = client.post("/api/volumes", files=files, data=chosen, headers=people["bob"]).json()
    # The same original UID gets the same new one, for everyone on this server.
    assert first["series"][0]["uid"] == again["series"][0]["uid"]
    mine = client.get(f"/api/volumes/{first['id']}/identity", headers=people["alice"])
    assert mine.status_code == 200
    record = mine.json()
    assert {k: record["patient"][k] for k in IDENTITY} == IDENTITY
    assert record["upload_filename"] == zip_path.name
    assert first["series"][0]["uid"] in record["uids"].values()
    assert set(record["uids"]) <= uids and len(record["uids"]) >= 2
    for headers in (people["bob"], {}):  # another user; the administrator (the client's own)
        r = client.get(f"/api/volumes/{first['id']}/identity", headers=headers)
        assert r.status_code == 404 and "Zebedee" not in r.text
    # Deleting the volume deletes the record.
    assert client.delete(f"/api/volumes/{first['id']}", headers=people["alice"]).status_code == 204
    assert client.app.state.store.get_identity(first["id"]) is None
