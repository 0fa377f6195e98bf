"""Identity that slipped past de-identification, uploaded to a real ``miss serve``: name
parts under three letters, dates spelled otherwise, IDs with their separators changed,
and free text in formats that have no identity fields (NIfTI ``descrip``, NRRD
``content``, file names). Nothing of it may come back from the API: volume and model
JSON, download file names, the share page's info."""

from __future__ import annotations

import gzip
import io
import re
import zipfile
from collections.abc import Iterator

import nibabel as nib
import numpy as np
import pytest
from corpus.files import dicom_bytes, dicom_slice
from support.realserver import Server, serving


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    folder = tmp_path_factory.mktemp("deid")
    with serving(folder / "data", folder / "server.log", env={"MISS_DEMO": "0"}) as running:
        yield running


def ct_series(description: str, **identity: str) -> bytes:
    """A zipped 6-slice CT series (a ramp with a bright block) carrying ``identity``."""
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w") as zf:
        for k in range(6):
            ds = dicom_slice(k, rows=16, columns=16)
            for keyword, value in identity.items():
                setattr(ds, keyword, value)
            ds.SeriesDescription = description
            zf.writestr(f"series/IM{k:04d}.dcm", dicom_bytes(ds))
    return out.getvalue()


def everything_shown(server: Server, volume: str) -> str:
    """All the API says about a volume: its JSON, the list, a model's JSON and download
    file name, and a share link's info, as one text."""
    said = [server.http.get(f"/api/volumes/{volume}").text, server.http.get("/api/volumes").text]
    job = server.http.post("/api/models", json={"volume": volume, "level": 500, "sample_rate": 1})
    model = job.json()["id"]
    server.wait(model, ("done", "failed"))
    said.append(server.http.get(f"/api/models/{model}").text)
    said.append(server.http.get(f"/api/models/{model}/model.stl").headers["content-disposition"])
    link = server.http.post("/api/shares", json={"model": model}).json()
    said.append(server.http.get(f"{link['url']}/info").text)
    return without_random("\n".join(said), link["url"].removeprefix("/s/"))


#: What the server makes up at random: hex ids, hashes and ETags; generated UIDs; clock
#: times. A random run of them may spell "roe" or "1970" and is no identity.
RANDOM = re.compile(
    r"\b[0-9a-f]{16,}\b|\b\d+(?:\.\d+){3,}\b"
    r"|\d{4}-\d\d-\d\d[T ]\d\d:\d\d:\d\d(?:\.\d+)?(?:Z|[+-]\d\d:\d\d)?"
)


#: Words of the API itself that spell a test's secret: the decimation method that made a
#: model (``"finished_with": "schroeder"`` holds "roe"), as a whole JSON string only.
VOCABULARY = ('"schroeder"',)


def without_random(text: str, token: str) -> str:
    """``text`` with the share token (random base64, which once held "roe"), the other
    random strings above and the API's own words that spell a secret replaced by
    placeholders."""
    for word in VOCABULARY:
        text = text.replace(word, '"WORD"')
    return RANDOM.sub("#", text.replace(token, "TOKEN"))


def words(text: str) -> set[str]:
    return {w.lower() for w in re.split(r"[^A-Za-z0-9]+", text) if w}


def test_short_name_parts_dates_and_ids_are_cut_everywhere(server: Server) -> None:
    """The finding: LI^NA survived in a file named NA_LI_head_CT (and so in model titles,
    download names and the share page); 1970-03-02 survived for 19700302."""
    identity = {"PatientName": "LI^NA", "PatientBirthDate": "19700302", "PatientID": "QX-77-31"}
    body = ct_series("head LI 1970-03-02 QX7731 2 Mar 1970", **identity)
    r = server.http.post("/api/volumes", files={"file": ("NA_LI_head_CT.zip", body)})
    assert r.status_code == 201, r.text
    shown = everything_shown(server, r.json()["id"])
    assert not {"li", "na", "qx7731"} & words(shown), shown[:2000]
    for spelling in ("1970-03-02", "19700302", "2 Mar 1970", "QX-77-31", "NA_LI"):
        assert spelling.lower() not in shown.lower(), spelling
    assert "head" in r.json()["series"][0]["description"].lower()  # the rest of it stays


def nifti(descrip: str) -> bytes:
    data = np.zeros((12, 12, 12), np.int16) - 1000
    data[3:9, 3:9, 3:9] = 1000
    image = nib.Nifti1Image(data, np.eye(4))
    image.header["descrip"] = descrip.encode()[:79]
    return gzip.compress(image.to_bytes())


@pytest.mark.parametrize(
    ("filename", "content", "secrets"),
    [
        ("brain.nii.gz", nifti("Roe^Jane 1970-03-02"), ["Roe", "Jane", "1970"]),
        ("brain.nii.gz", nifti("Patient: Jane Roe, T1"), ["Roe", "Jane"]),
        ("Roe^Jane_1970-03-02.nii.gz", nifti("T1 axial"), ["Roe", "Jane", "1970"]),
        ("scan 02.03.1970.nii.gz", nifti("T1 axial"), ["1970"]),
    ],
)
def test_free_text_of_formats_without_identity_fields(
    server: Server, filename: str, content: bytes, secrets: list[str]
) -> None:
    """NIfTI ``descrip`` and file names: names and dates go by pattern, since there is
    no identity to match them against; a volume whose file name carried them is named by
    its modality and upload time instead."""
    r = server.http.post("/api/volumes", files={"file": (filename, content)})
    assert r.status_code == 201, r.text
    shown = everything_shown(server, r.json()["id"])
    for secret in secrets:
        assert secret.lower() not in shown.lower(), (secret, shown[:1500])


def test_nrrd_content_is_cleaned(server: Server) -> None:
    data = np.zeros((10, 10, 10), np.int16) - 1000
    data[2:8, 2:8, 2:8] = 1000
    header = (
        b"NRRD0004\ntype: short\ndimension: 3\nsizes: 10 10 10\nencoding: raw\n"
        b"endian: little\nspace: left-posterior-superior\n"
        b"space directions: (1,0,0) (0,1,0) (0,0,1)\nspace origin: (0,0,0)\n"
        b"content: Doe^John born 1970-03-02\n\n"
    )
    r = server.http.post("/api/volumes", files={"file": ("head.nrrd", header + data.tobytes())})
    assert r.status_code == 201, r.text
    shown = everything_shown(server, r.json()["id"])
    for secret in ("doe", "john", "1970"):
        assert secret not in shown.lower(), secret
    assert "[removed]" in r.json()["series"][0]["description"]  # said, not silently gone
