"""Identity spelled otherwise than in the header, uploaded to a real ``miss serve``:
"MÜLLER^JÖRG" as "Mueller Joerg" or "MULLER JORG"; a Unicode "Müller^Jörg" where no
header names anyone; a name and a date in a series whose PatientName is empty; a second
patient's series in the same zip; the patient's name as the file's; a header value quoted
in a pydicom warning. Nothing of it may come back from what the server serves: the
volume's JSON (its notes and series list), the volume list, model JSON and download
name, the share page, the audit log and the provenance inside the model's GLB."""

from __future__ import annotations

import gzip
import io
import json
import re
import subprocess
import sys
import warnings
import zipfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from corpus.files import OTHER_SERIES_UID, dicom_bytes, dicom_slice
from fastapi.testclient import TestClient
from support.pg import settings_for
from support.realserver import Server
from test_deid_attacks import RANDOM, ct_series, everything_shown, nifti
from test_deid_attacks import server as server  # the fixture: one real server for the file
from test_tiles import glb_json

from miss.server.app import create_app

#: Header values in UTF-8, as a German scanner may write them.
UTF8 = {"SpecificCharacterSet": "ISO_IR 192"}
#: The ``upload`` fixture: (file name, content) -> the new volume's JSON.
Upload = Callable[..., dict[str, Any]]
#: Every spelling of MÜLLER^JÖRG that must not come back, and the fragments a cut leaves.
MUELLER = ["müller", "mueller", "muller", "jörg", "jørg", "joerg", "jorg", "mü", "örg"]


def strings(value: Any) -> list[str]:
    """Every string in a JSON value (its numbers left out: a byte length may spell 1970)."""
    if isinstance(value, dict):
        return [s for k, v in value.items() for s in (str(k), *strings(v))]
    if isinstance(value, list):
        return [s for v in value for s in strings(v)]
    return [value] if isinstance(value, str) else []


def served(server: Server, volume: str) -> str:
    """All that is served about a volume (``everything_shown``), its audit entries and
    the text of its models' GLB (names, provenance), lower-cased."""
    said = [everything_shown(server, volume)]
    models = server.http.get("/api/models", params={"volume": volume}).json()
    for model in models:
        glb = server.http.get(f"/api/models/{model['id']}/model.glb")
        assert glb.status_code == 200, glb.text
        document = glb_json(glb.content)
        assert any("provenance" in n.get("extras", {}) for n in document["nodes"])
        said.append(RANDOM.sub("#", "\n".join(strings(document))))
    ours = {volume, *(m["id"] for m in models)}  # this volume's entries, not the others'
    audit = server.http.get("/api/audit").json()
    details = [e["detail"] for e in audit if ours & {e["target"], e["detail"].get("volume")}]
    assert details  # the upload, the model, its downloads and share were audited
    said.append(RANDOM.sub("#", "\n".join(strings(details))))
    return "\n".join(said).lower()


@pytest.fixture
def upload(server: Server) -> Iterator[Upload]:
    """Upload a file as the administrator; the volumes go at the end of the test, so the
    volume list of the next one shows only its own."""
    made: list[str] = []

    def send(filename: str, content: bytes, **fields: str) -> dict[str, Any]:
        r = server.http.post("/api/volumes", files={"file": (filename, content)}, data=fields)
        assert r.status_code == 201, r.text
        made.append(r.json()["id"])
        return dict(r.json())

    yield send
    for volume in made:
        assert server.http.delete(f"/api/volumes/{volume}").status_code == 204


def assert_gone(shown: str, secrets: list[str]) -> None:
    for secret in secrets:
        at = shown.find(secret)
        assert at < 0, (secret, shown[max(0, at - 200) : at + 200])


@pytest.mark.parametrize(
    ("header", "description"),
    [
        ("MÜLLER^JÖRG", "Mueller Joerg head"),
        ("MÜLLER^JÖRG", "MULLER JORG head"),
        ("MÜLLER^JÖRG", "Jørg Müller head"),
        ("MUELLER^JOERG", "Müller Jörg head"),
    ],
)
def test_a_name_in_another_spelling_than_the_headers(
    server: Server, upload: Upload, header: str, description: str
) -> None:
    """The finding: the header said MÜLLER^JÖRG, the description "Mueller Joerg head" or
    "MULLER JORG head", and the description came back whole."""
    volume = upload("head.zip", ct_series(description, **UTF8, PatientName=header))
    assert_gone(served(server, volume["id"]), MUELLER)
    assert volume["series"][0]["description"].endswith("head")  # the rest of it stays


@pytest.mark.parametrize("descrip", ["Müller^Jörg T1", "T1 Müller^Jörg", "Müller^Jörg"])
def test_a_unicode_person_name_where_no_header_names_anyone(
    server: Server, upload: Upload, descrip: str
) -> None:
    """The finding: "Müller^Jörg" in a NIfTI ``descrip`` was stored as
    "Mü[removed]örg": the person-name pattern knew only ASCII letters."""
    volume = upload("brain.nii.gz", nifti_latin1(descrip))
    assert_gone(served(server, volume["id"]), MUELLER)
    assert "[removed]" in volume["series"][0]["description"]


def nifti_latin1(descrip: str) -> bytes:
    """``nifti`` with its ``descrip`` in Latin-1, as the reader decodes it."""
    plain = bytearray(gzip.decompress(nifti("")))
    raw = descrip.encode("latin-1")[:79]
    plain[148 : 148 + len(raw)] = raw
    return gzip.compress(bytes(plain))


def test_a_name_and_date_in_a_series_whose_patient_name_is_empty(
    server: Server, upload: Upload
) -> None:
    """The finding: PatientName empty, "Doe^John head 02.03.1970" in the description, and
    DICOM descriptions were matched against the (empty) header only."""
    body = ct_series("Doe^John head 02.03.1970", PatientName="", PatientID="")
    volume = upload("head.zip", body)
    assert_gone(served(server, volume["id"]), ["doe", "john", "1970", "02.03"])


def two_patients() -> bytes:
    """A zip of two series: six slices of Anna Smith's head, three of Jane Roe's scout
    (whose description names her otherwise than her header, with her ID and birth date)."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for k in range(6):
            ds = dicom_slice(k, rows=16, columns=16)
            ds.PatientName, ds.PatientID, ds.SeriesDescription = "Smith^Anna", "AS-1", "head"
            zf.writestr(f"a/IM{k + 1:04d}.dcm", dicom_bytes(ds))
        for k in range(3):
            ds = dicom_slice(k, rows=16, columns=16, series_uid=OTHER_SERIES_UID)
            ds.PatientName, ds.PatientID = "Roe^Jane", "RJ-5501"
            ds.PatientBirthDate = "19800101"
            ds.SeriesDescription = "Jane Roe scout RJ5501 1 Jan 1980"
            zf.writestr(f"b/IM{k:04d}.dcm", dicom_bytes(ds))
    return out.getvalue()


def test_every_series_of_an_upload_is_scrubbed(server: Server, upload: Upload) -> None:
    """The finding: a second series of another patient in the same zip kept "Roe^Jane
    scout 1980-01-01" in the volume's series list: only the series read was matched."""
    # Asked which series to read, the list of them carries no identity either.
    asked = server.http.post("/api/volumes", files={"file": ("study.zip", two_patients())})
    assert asked.status_code == 409, asked.text
    assert_gone(asked.text.lower(), ["roe", "jane", "rj5501", "rj-5501", "1980", "smith", "anna"])
    assert sorted(s["slices"] for s in asked.json()["series"]) == [3, 6]
    volume = upload("study.zip", two_patients(), series=asked.json()["series"][0]["uid"])
    assert len(volume["series"]) == 2
    shown = served(server, volume["id"])
    assert_gone(shown, ["roe", "jane", "rj5501", "rj-5501", "1980", "smith", "anna"])
    assert any(s["description"].endswith("scout [removed] [removed]") for s in volume["series"])


@pytest.mark.parametrize(
    ("filename", "content", "secrets"),
    [
        ("Smith_John_1970.zip", ct_series("head", PatientName=""), ["smith", "john", "1970"]),
        ("Jörg Müller.nii.gz", nifti("T1 axial"), MUELLER),
        ("Jörg Müller.zip", ct_series("", PatientName=""), MUELLER),
    ],
)
def test_file_names_name_no_volume(
    server: Server, upload: Upload, filename: str, content: bytes, secrets: list[str]
) -> None:
    """The finding: "Smith_John_1970.zip" and "Jörg Müller.nii" became volume names,
    and so audit entries, model titles and GLB provenance; the header named nobody to
    match them against. The name is the owner's alone now, in the identity record."""
    volume = upload(filename, content)
    assert_gone(served(server, volume["id"]), secrets)
    # Named by what the scan says: modality and description, else the upload's time.
    assert re.fullmatch(r"CT head|(CT )?T1 axial|CT volume, uploaded .*", volume["name"])
    record = server.http.get(f"/api/volumes/{volume['id']}/identity")  # the owner: admin
    assert record.status_code == 200 and record.json()["upload_filename"] == filename


def test_pydicom_warnings_quote_no_header_value(server: Server, upload: Upload) -> None:
    """The finding: pydicom's "Invalid value for VR UI: 'Jane Roe'" went into the notes
    whole; a value in the wrong field is no identity the header names."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pydicom warns of the bad value as it is written
        for k in range(6):
            ds = dicom_slice(k, rows=16, columns=16)
            ds.PatientName = ""
            ds.add_new(0x00081150, "UI", "Jane Roe")  # ReferencedSOPClassUID, misfilled
            zf.writestr(f"s/IM{k:04d}.dcm", dicom_bytes(ds))
    volume = upload("scan.zip", out.getvalue())
    assert any("pydicom" in note for note in volume["notes"]), volume["notes"]  # a warning
    assert_gone(served(server, volume["id"]), ["jane", "roe"])
    assert json.dumps(volume["notes"]).count("[value]")


def test_miss_ingest_names_no_volume_by_its_folder(
    tmp_path: Path, login: Callable[..., TestClient], admin_password: str
) -> None:
    """The finding's folder half: ``miss ingest Smith_John_1970/`` listed the volume as
    "Smith_John_1970", the header naming nobody to match it against."""
    folder = tmp_path / "Smith_John_1970"
    folder.mkdir()
    for k in range(6):
        ds = dicom_slice(k, rows=16, columns=16)
        ds.PatientName, ds.PatientID, ds.SeriesDescription = "", "", "head"
        (folder / f"IM{k:04d}.dcm").write_bytes(dicom_bytes(ds))
    data = tmp_path / "data"
    run = subprocess.run(
        [sys.executable, "-m", "miss", "ingest", str(folder), "--data-dir", str(data)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    settings = settings_for(data, admin_password=admin_password, demo=False)
    with TestClient(create_app(settings)) as client:
        login(client)
        shown = client.get("/api/volumes").text + client.get("/api/audit").text
        (volume,) = client.get("/api/volumes").json()
        assert volume["name"] == "CT head"
        assert_gone(shown.lower(), ["smith", "john"])
        record = client.get(f"/api/volumes/{volume['id']}/identity")  # the first admin's
        assert record.status_code == 200 and record.json()["upload_filename"] == folder.name
