"""Bad input over the HTTP API: every JSON endpoint, model-job parameters, uploads (also a
2 GB+ stream against a real ``miss serve``) and the bad-file corpus.

Every case: a 4xx (never a 5xx) whose JSON ``detail`` is one readable sentence naming the
problem, and nothing stored changes (volumes, models, shares, users; an existing model
still downloads the same bytes; nothing left in ``tmp/``).
"""

from __future__ import annotations

import gzip
import hashlib
import json
import select
import signal
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from corpus.cases import generate
from corpus.upload import as_upload
from fastapi.testclient import TestClient
from support import ADMIN_PASSWORD
from support.pg import copy_seed, settings_for
from support.realserver import Server

from miss.server.app import create_app
from miss.server.core.schemas import MAX_JSON_BYTES
from miss.spec import MAX_LEVELS

#: High enough that the rate limiter never answers in place of the code under test.
UNLIMITED = {"api_rate": 1e6, "api_burst": 1e6}
FAST = {"level": 300, "sample_rate": 4, "decimate": "none"}
#: Values of the wrong type for any field: null, a list, nested garbage, a number too
#: large for any float.
GARBAGE: list[Any] = [None, [1, "two", None], {"deep": {"er": [{"x": None}, []]}}, 10**400]


def log_in(client: TestClient) -> None:
    r = client.post("/api/auth/login", json={"username": "admin", "password": ADMIN_PASSWORD})
    assert r.status_code == 200, r.text
    client.cookies.clear()
    client.headers["Authorization"] = f"Bearer {r.json()['token']}"


def refused(r: httpx.Response, *words: str, codes: tuple[int, ...] = ()) -> str:
    """Assert a 4xx with a readable string ``detail`` containing ``words``; returns it."""
    assert 400 <= r.status_code < 500, f"{r.status_code}: {r.text[:500]}"
    if codes:
        assert r.status_code in codes, f"{r.status_code}: {r.text[:500]}"
    assert r.headers["content-type"].startswith("application/json"), r.headers
    detail = r.json()["detail"]
    assert isinstance(detail, str) and len(detail) >= 12, detail
    assert "Traceback" not in detail and "Input should be a valid dictionary" not in detail
    for word in words:
        assert word.lower() in detail.lower(), f"{word!r} not in {detail!r}"
    return detail


def label_nifti() -> bytes:
    """A 20^3 label map (labels 1 and 2) as .nii.gz: a volume that is its own label map."""
    import nibabel as nib

    labels = np.zeros((20, 20, 20), np.uint8)
    labels[3:9, 3:9, 3:9] = 1
    labels[11:17, 11:17, 11:17] = 2
    return gzip.compress(nib.Nifti1Image(labels, np.eye(4)).to_bytes())


class Site:
    """The module's app and what it holds before any bad request."""

    def __init__(self, client: TestClient) -> None:
        self.c = client
        self.data = Path(client.app.state.settings.data_dir)
        volumes = client.get("/api/volumes").json()
        self.demo = volumes[0]
        r = client.post("/api/models", json={"volume": self.demo["id"], **FAST})
        assert r.status_code in (200, 202), r.text
        self.model = self._wait(r.json()["id"])
        r = client.post("/api/volumes", files={"file": ("labels.nii.gz", label_nifti())})
        assert r.status_code == 201, r.text
        self.labels = r.json()
        r = client.post("/api/shares", json={"model": self.model["id"], "expires_in": 3600})
        assert r.status_code == 201, r.text
        self.before = self.snapshot()

    def _wait(self, model_id: str) -> dict[str, Any]:
        deadline = time.monotonic() + 120
        while (body := self.c.get(f"/api/models/{model_id}").json())["status"] not in (
            "done",
            "failed",
        ):
            assert time.monotonic() < deadline, body
            time.sleep(0.1)
        assert body["status"] == "done", body
        return body

    def snapshot(self) -> dict[str, Any]:
        c = self.c
        glb = c.get(f"/api/models/{self.model['id']}/model.glb")
        assert glb.status_code == 200
        return {
            "volumes": sorted(v["id"] for v in c.get("/api/volumes").json()),
            "models": sorted(m["id"] for m in c.get("/api/models").json()),
            "shares": sorted(s["id"] for s in c.get("/api/shares").json()),
            "users": sorted(u["name"] for u in c.get("/api/users").json()),
            "glb": hashlib.sha256(glb.content).hexdigest(),
            "tmp": sorted(p.name for p in (self.data / "tmp").iterdir()),
        }

    def unchanged(self) -> None:
        assert self.snapshot() == self.before


@pytest.fixture(scope="module")
def site(seeded_dir: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Site]:
    data = copy_seed(seeded_dir, tmp_path_factory.mktemp("bad-input") / "data")
    settings = settings_for(data, admin_password=ADMIN_PASSWORD, **UNLIMITED)
    with TestClient(create_app(settings)) as c:
        log_in(c)
        yield Site(c)


# -- JSON bodies of every endpoint ---------------------------------------------------------


def valid_bodies(site: Site) -> dict[str, dict[str, Any]]:
    """A body each JSON endpoint accepts (the model's is the model that exists)."""
    return {
        "/api/models": {"volume": site.demo["id"], **FAST},
        "/api/shares": {"model": site.model["id"], "expires_in": 3600, "label": "x"},
        "/api/auth/login": {"username": "admin", "password": ADMIN_PASSWORD},
        "/api/users": {"name": "carol", "password": "carol-password"},
    }


ENDPOINTS = ["/api/models", "/api/shares", "/api/auth/login", "/api/users"]
#: Fields whose null is the default (so null is no error there).
NULLABLE = {
    "/api/models": {"start_slice", "end_slice", "levels", "labels", "smooth"},
    "/api/shares": {"volume"},
}
JSON = {"content-type": "application/json"}
BIG = {"pad": "x" * (1 << 20)}

#: (name, raw body, headers, words the detail must contain)
MALFORMED: list[tuple[str, bytes | None, dict[str, str], tuple[str, ...]]] = [
    ("not-json", b"this is not JSON", JSON, ("not valid JSON",)),
    ("truncated-json", b'{"volume": "ab', JSON, ("not valid JSON",)),
    ("empty", b"", JSON, ("empty",)),
    ("json-null", b"null", JSON, ("JSON object", "null")),
    ("json-list", b"[1, 2, 3]", JSON, ("JSON object", "list")),
    ("json-string", b'"volume"', JSON, ("JSON object",)),
    ("json-number", b"42", JSON, ("JSON object",)),
    ("nan-literal", b"NaN", JSON, ("JSON object",)),
    ("text-plain", None, {"content-type": "text/plain"}, ("Content-Type",)),
    ("no-content-type", None, {"content-type": ""}, ()),
    (
        "form-urlencoded",
        b"volume=x&level=3",
        {"content-type": "application/x-www-form-urlencoded"},
        ("Content-Type",),
    ),  # fmt: skip
    ("xml", b"<volume>x</volume>", {"content-type": "application/xml"}, ("Content-Type",)),
    ("deep-nesting", b"[" * 50_000, JSON, ("JSON",)),
    ("over-64KB", b"", JSON, ("64 KB",)),  # the body is made below
]


@pytest.mark.parametrize("endpoint", ENDPOINTS)
@pytest.mark.parametrize(
    ("case", "raw", "headers", "words"), MALFORMED, ids=[m[0] for m in MALFORMED]
)
def test_malformed_bodies(
    site: Site,
    endpoint: str,
    case: str,
    raw: bytes | None,
    headers: dict[str, str],
    words: tuple[str, ...],
) -> None:
    valid = valid_bodies(site)[endpoint]
    if raw is None:  # a good body under the wrong (or no) content type
        raw = json.dumps(valid).encode()
    if case == "over-64KB":
        raw = json.dumps({**valid, **BIG}).encode()
    send = {"Authorization": site.c.headers["Authorization"], **headers}
    r = site.c.post(endpoint, content=raw, headers={k: v for k, v in send.items() if v})
    refused(r, *words)
    site.unchanged()


@pytest.mark.parametrize("endpoint", ENDPOINTS)
def test_streamed_json_over_the_cap_is_413(site: Site, endpoint: str) -> None:
    """Without a Content-Length the cap counts what arrives (no 1 MB held first)."""

    def chunks() -> Iterator[bytes]:
        yield b'{"pad": "'
        for _ in range(16):
            yield b"x" * 65536
        yield b'"}'

    r = site.c.post(endpoint, content=chunks(), headers=JSON)
    refused(r, f"{MAX_JSON_BYTES // 1024} KB", codes=(413,))
    site.unchanged()


def field_cases() -> list[tuple[str, str, int]]:
    """(endpoint, field, index in GARBAGE) for every field of every valid body."""
    fields = {
        "/api/models": ["volume", "level", "sample_rate", "start_slice", "end_slice", "decimate",
                        "error_bound", "reduce", "levels", "components", "min_size_mm3",
                        "smooth", "passband", "labels"],
        "/api/shares": ["model", "volume", "expires_in", "can_download", "can_annotate", "label"],
        "/api/auth/login": ["username", "password"],
        "/api/users": ["name", "password", "admin"],
    }  # fmt: skip
    return [
        (endpoint, field, i)
        for endpoint, names in fields.items()
        for field in names
        for i, value in enumerate(GARBAGE)
        if not (value is None and field in NULLABLE.get(endpoint, ()))
    ]


@pytest.mark.parametrize(("endpoint", "field", "which"), field_cases())
def test_wrong_types_in_every_field(site: Site, endpoint: str, field: str, which: int) -> None:
    body = {**valid_bodies(site)[endpoint], field: GARBAGE[which]}
    r = site.c.post(endpoint, content=json.dumps(body).encode(), headers=JSON)
    detail = refused(r)
    if r.status_code == 422 and "errors" in r.json():  # FastAPI's check: names the field
        assert field in detail, detail
    site.unchanged()


@pytest.mark.parametrize("endpoint", ENDPOINTS)
def test_unknown_and_missing_fields(site: Site, endpoint: str) -> None:
    valid = valid_bodies(site)[endpoint]
    r = site.c.post(endpoint, json={**valid, "colour": "red", "nested": {"a": [1, {"b": 2}]}})
    refused(r, "'colour' is not a field", "'nested'", codes=(422,))
    required = {"/api/models": ["volume"], "/api/auth/login": ["username", "password"],
                "/api/users": ["name", "password"]}.get(endpoint, [])  # fmt: skip
    for name in required:
        r = site.c.post(endpoint, json={k: v for k, v in valid.items() if k != name})
        refused(r, f"'{name}' is required", codes=(422,))
    site.unchanged()


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e400", "-1e999"])
@pytest.mark.parametrize("field", ["level", "error_bound", "reduce", "passband", "min_size_mm3"])
def test_non_finite_numbers(site: Site, field: str, literal: str) -> None:
    """Python's JSON reads NaN and Infinity literals (and 1e400 as inf): none gets in."""
    body = json.dumps({"volume": site.demo["id"], **FAST, field: 0}).replace(
        f'"{field}": 0', f'"{field}": {literal}'
    )
    r = site.c.post("/api/models", content=body.encode(), headers=JSON)
    refused(r, field, "finite", codes=(422,))
    levels = json.dumps({"volume": site.demo["id"], "levels": [300, 0]})
    r = site.c.post(
        "/api/models", content=levels.replace("0]", f"{literal}]").encode(), headers=JSON
    )
    refused(r, "levels[1]", "finite", codes=(422,))
    site.unchanged()


# -- model-job parameters out of range -----------------------------------------------------

OUT_OF_RANGE: list[tuple[dict[str, Any], str]] = [
    ({"sample_rate": 0}, "sample_rate must be an integer >= 1"),
    ({"sample_rate": -2}, "sample_rate must be an integer >= 1"),
    ({"sample_rate": 10**6}, "at least 2 along each axis"),
    ({"sample_rate": 10**40}, "at least 2 along each axis"),
    ({"sample_rate": [1, 2]}, "three of them"),
    ({"sample_rate": [1, 1, 0]}, "sample_rate"),
    ({"sample_rate": 2.5}, "'sample_rate' should be a whole number or a list"),
    ({"reduce": 1.5}, "reduce must be in [0, 1)"),
    ({"reduce": -0.1}, "reduce must be in [0, 1)"),
    ({"reduce": 1.0}, "reduce must be in [0, 1)"),
    ({"error_bound": 0}, "error_bound must be > 0"),
    ({"error_bound": -1e-3}, "error_bound must be > 0"),
    ({"start_slice": 60, "end_slice": 20}, "swap"),
    ({"start_slice": 129}, "beyond the volume's 128 slices; use 1..128"),
    ({"end_slice": 10**30}, "beyond the volume's 128 slices"),
    ({"start_slice": 0}, "1-based"),
    ({"end_slice": -5}, "1-based"),
    ({"start_slice": 1, "end_slice": 8}, "no surface at level 300 in slices 1..8"),
    ({"level": 5000}, "outside this volume's values -1024..1126 HU"),
    ({"level": -1e6}, "outside this volume's values -1024..1126 HU"),
    ({"level": None, "levels": [300, 9000]}, "level 9000 is outside this volume's values -1024..1126"),
    ({"level": None, "levels": [300.0] * (MAX_LEVELS + 1)}, f"at most {MAX_LEVELS}"),
    ({"level": None, "levels": [0.5] * 10_000}, f"at most {MAX_LEVELS}"),
    ({"level": None, "levels": []}, "needs a 'level'"),
    ({"level": None}, "needs a 'level'"),
    ({"decimate": "magic"}, "decimate must be one of"),
    ({"decimate": ""}, "decimate must be one of"),
    ({"components": "every"}, "components must be one of all, largest, split"),
    ({"format": "dxf"}, "'format' is not a field"),
    ({"formats": ["glb"]}, "'formats' is not a field"),
    ({"method": "marching"}, "'method' is not a field"),
    ({"smooth": -1}, "smooth must be a whole number"),
    ({"smooth": 10**6}, "far beyond useful"),
    ({"passband": 0}, "passband must be in (0, 2)"),
    ({"passband": 2.5}, "passband must be in (0, 2)"),
    ({"min_size_mm3": -1}, "min size must be a volume in mm³ >= 0"),
    ({"labels": "bogus"}, "labels must be 'all' or label numbers"),
    ({"labels": [0]}, "0 is background"),
    ({"labels": [-3, 2]}, "0 is background"),
    ({"labels": []}, "0 is background"),
    ({"labels": "all"}, "no label map"),
    ({"volume": "no-such-volume"}, "no volume 'no-such-volume'"),
]  # fmt: skip


@pytest.mark.parametrize(("change", "words"), OUT_OF_RANGE, ids=[w for _, w in OUT_OF_RANGE])
def test_model_parameters_out_of_range(site: Site, change: dict[str, Any], words: str) -> None:
    body = {"volume": site.demo["id"], **FAST, **change}
    body = {k: v for k, v in body.items() if not (k == "level" and v is None)}
    refused(site.c.post("/api/models", json=body), words)
    site.unchanged()


def test_labels_not_in_the_label_map(site: Site) -> None:
    vid = site.labels["id"]
    for labels in ([999], [3, 4], [10**30], "7,8"):
        r = site.c.post("/api/models", json={"volume": vid, "labels": labels})
        refused(r, "none of the labels", "it holds 1, 2", codes=(422,))
    r = site.c.post("/api/models", json={"volume": vid, "labels": [1.5]})
    refused(r, "'labels'", codes=(422,))
    site.unchanged()


def test_share_and_user_values_out_of_range(site: Site) -> None:
    model = site.model["id"]
    for body, words in [
        ({"model": model, "expires_in": 0}, "out of range"),
        ({"model": model, "expires_in": -60}, "out of range"),
        ({"model": model, "expires_in": 10**30}, "out of range"),
        ({"model": model, "expires_in": 3600.5}, "'expires_in' should be a whole number"),
        ({}, "exactly one"),
        ({"model": model, "volume": site.demo["id"]}, "exactly one"),
        ({"model": "nope", "volume": "nope"}, "exactly one"),
        ({"model": "nope"}, "no model 'nope'"),
        ({"volume": "nope"}, "no volume 'nope'"),
        ({"model": model, "label": "x" * 201}, "'label'"),
    ]:
        refused(site.c.post("/api/shares", json=body), words)
    for body, words in [
        ({"name": "", "password": "long-enough-password"}, "not valid"),
        ({"name": "../etc", "password": "long-enough-password"}, "not valid"),
        ({"name": "a\x00b", "password": "long-enough-password"}, "not valid"),
        ({"name": "x" * 65, "password": "long-enough-password"}, "'name'"),
        ({"name": "admin", "password": "long-enough-password"}, "exists already"),
        ({"name": "dave", "password": "p" * 1025}, "'password'"),
    ]:
        refused(site.c.post("/api/users", json=body), words)
    for body in [
        {"username": "x" * 65, "password": "p"},
        {"username": "a", "password": "p" * 1025},
    ]:
        refused(site.c.post("/api/auth/login", json=body), codes=(422,))
    secret = "s3cret-" * 200  # too long: refused, and never echoed back
    for path, body in [
        ("/api/auth/login", {"username": "admin", "password": secret}),
        ("/api/users", {"name": "erin", "password": secret}),
    ]:
        detail = refused(site.c.post(path, json=body), "'password'", codes=(422,))
        assert "s3cret" not in detail
    site.unchanged()


def test_query_and_path_parameters(site: Site) -> None:
    vid, mid = site.demo["id"], site.model["id"]
    base = f"/api/volumes/{vid}/slices"
    for path, words in [
        (f"{base}/axial/128.png", "outside 0..127"),
        (f"{base}/axial/99999999999999999999999.png", "outside 0..127"),
        (f"{base}/axial/-1.png", "outside"),
        (f"{base}/axial/three.png", "'index' (path parameter) should be a whole number"),
        (f"{base}/oblique/3.png", "'axis'"),
        (f"{base}/axial/3.png?window=NaN", "'window' (query parameter) should be a finite"),
        (f"{base}/axial/3.png?window=-5", "'window'"),
        (f"{base}/axial/3.png?window=5e-324&level=0", "'window'"),
        (f"{base}/axial/3.png?window=1e308&level=1e308", "'level'"),
        (f"{base}/axial/3.png?threshold=-1e300", "'threshold'"),
        (f"{base}/axial/3.png?level=Infinity", "'level'"),
        (f"{base}/axial/3.png?threshold=1e400", "'threshold'"),
        (f"{base}/axial/3.png?size=0", "'size'"),
        (f"{base}/axial/3.png?size=100000", "'size'"),
        (f"/api/models/{mid}/room/events?session=0", "'session'"),
        (f"/api/models/{mid}/room/events?session=99999999999999999999", "'session'"),
        (f"/api/models/{mid}/room/events?session=abc", "'session'"),
        (f"/api/models/{mid}/model.dxf", "no format 'dxf'"),
        ("/api/models?volume=nope", "no volume 'nope'"),
        ("/api/no/such/route", "no such page or API route"),
    ]:
        refused(site.c.get(path), words)
    refused(site.c.delete("/api/auth/login"), "DELETE is not allowed", codes=(405,))
    refused(site.c.put("/api/models", json={}), "PUT is not allowed", codes=(405,))
    site.unchanged()


# -- uploads -------------------------------------------------------------------------------


def multipart(*parts: tuple[bytes, bytes], boundary: bytes = b"bnd7") -> bytes:
    """A multipart body from (Content-Disposition value, content) pairs, written by hand
    so that names can be any bytes."""
    out = b""
    for disposition, content in parts:
        out += b"--" + boundary + b"\r\nContent-Disposition: " + disposition + b"\r\n\r\n"
        out += content + b"\r\n"
    return out + b"--" + boundary + b"--\r\n"


MULTIPART = {"content-type": "multipart/form-data; boundary=bnd7"}


def file_part(name: bytes, content: bytes) -> tuple[bytes, bytes]:
    return b'form-data; name="file"; filename="' + name + b'"', content


BAD_UPLOADS: list[tuple[str, bytes, dict[str, str], tuple[int, ...], str]] = [
    ("zero-byte-file", multipart(file_part(b"scan.nii.gz", b"")), MULTIPART, (422,), "empty"),
    ("empty-multipart", b"--bnd7--\r\n", MULTIPART, (422,), "no file"),
    ("empty-body", b"", MULTIPART, (422,), "no file"),
    ("no-file-part", multipart((b'form-data; name="name"', b"a name")), MULTIPART, (422,),
     "field 'file'"),
    ("file-part-without-filename", multipart((b'form-data; name="file"', b"abc")), MULTIPART,
     (422,), "field 'file'"),
    # several file parts are one upload (the slices of a series), but not two volumes
    ("two-file-parts", multipart(file_part(b"a.nii", b"a"), file_part(b"b.nii", b"b")),
     MULTIPART, (422,), ("several volumes", "exactly one file")),  # volume, label map
    ("missing-boundary", multipart(file_part(b"a.nii", b"a")),
     {"content-type": "multipart/form-data"}, (415,), "multipart/form-data"),
    ("wrong-boundary", multipart(file_part(b"a.nii", b"a"), boundary=b"other"), MULTIPART,
     (400,), "malformed"),
    ("garbage-body", b"garbage, not multipart", MULTIPART, (400,), "malformed"),
    ("boundary-too-long", b"x", {"content-type": "multipart/form-data; boundary=" + "b" * 400},
     (400,), "malformed"),
    ("json-instead", b'{"file": "x"}', {"content-type": "application/json"}, (415,),
     "multipart"),
    ("no-content-type", b"abc", {}, (415,), "multipart"),
    ("too-many-fields", multipart(*[(b'form-data; name="f%d"' % i, b"v") for i in range(40)]),
     MULTIPART, (422,), "too many form fields"),
    ("long-field", multipart((b'form-data; name="name"', b"n" * 70_000)), MULTIPART, (422,),
     "longer than"),
    ("header-too-long", multipart((b'form-data; name="file"; filename="' + b"a" * 20_000
                                   + b'.nii"', b"abc")), MULTIPART, (400,), "malformed"),
    ("text-file-non-utf8-name", multipart(file_part(b"\xff\xfe\xc3(scan.txt", b"hello\n" * 50)),
     MULTIPART, (415, 422), ""),
    ("dotdot-name-bad-content", multipart(file_part(b"../../../etc/passwd", b"root:x:0:0")),
     MULTIPART, (415, 422), ""),
    ("absolute-name-bad-content", multipart(file_part(b"/etc/shadow.nii", b"x" * 10)),
     MULTIPART, (422,), "shadow.nii: "),
    ("nul-in-name", multipart(file_part(b"a\x00b.nii.gz", b"\x1f\x8b broken gzip")), MULTIPART,
     (415, 422), ""),
]  # fmt: skip


@pytest.mark.parametrize(
    ("case", "body", "headers", "codes", "words"), BAD_UPLOADS, ids=[b[0] for b in BAD_UPLOADS]
)
def test_bad_uploads(
    site: Site,
    case: str,
    body: bytes,
    headers: dict[str, str],
    codes: tuple[int, ...],
    words: str | tuple[str, str],
) -> None:
    send = {"Authorization": site.c.headers["Authorization"], **headers}
    paths = ("/api/volumes", f"/api/volumes/{site.demo['id']}/labelmap")
    said = words if isinstance(words, tuple) else (words, words)  # for each path
    for path, word in zip(paths, said, strict=True):
        r = site.c.post(path, content=body, headers=send)
        detail = refused(r, word, codes=codes)
        assert str(site.data) not in detail  # no server paths in answers
        site.unchanged()


@pytest.mark.parametrize(
    "name",
    [b"../../escape.nii.gz", b"/etc/abs.nii.gz", b"..\\..\\win.nii.gz", b"\xff\xfe\xc3(.nii.gz",
     b"con:aux|*?.nii.gz", b"a" * 300 + b".nii.gz"],
    ids=["dotdot", "absolute", "backslashes", "non-utf8", "odd-chars", "long"],
)  # fmt: skip
def test_odd_file_names_of_a_good_volume(site: Site, name: bytes, small_nifti: bytes) -> None:
    """A good scan under a hostile name is stored inside the data folder under a safe name."""
    outside = site.data.parent
    before = sorted(p.name for p in outside.iterdir())
    send = {"Authorization": site.c.headers["Authorization"], **MULTIPART}
    r = site.c.post("/api/volumes", content=multipart(file_part(name, small_nifti)), headers=send)
    assert r.status_code == 201, r.text
    body = r.json()
    assert "/" not in body["name"] and "\\" not in body["name"] and ".." not in body["name"]
    assert 0 < len(body["name"]) <= 200 and body["name"].isprintable()
    assert sorted(p.name for p in outside.iterdir()) == before  # nothing written beside data/
    assert not list(Path("/etc").glob("abs.nii*"))
    assert site.c.delete(f"/api/volumes/{body['id']}").status_code == 204
    site.unchanged()


def test_upload_over_the_limit_streams_and_stops(make_client, small_nifti: bytes) -> None:
    """A body over ``max_upload_mb`` (sent as a stream, never whole in this process) is a
    413 and leaves nothing; a good upload still works after it."""
    c = make_client(max_upload_mb=1, **UNLIMITED)
    data = Path(c.app.state.settings.data_dir)

    def zeros() -> Iterator[bytes]:
        yield b'--bnd7\r\nContent-Disposition: form-data; name="file"; filename="big.nii"\r\n\r\n'
        for _ in range(8):
            yield bytes(1 << 19)
        yield b"\r\n--bnd7--\r\n"

    r = c.post("/api/volumes", content=zeros(), headers=MULTIPART)
    refused(r, "limit of 1 MB", "MISS_MAX_UPLOAD_MB", codes=(413,))
    assert sorted((data / "tmp").iterdir()) == []
    assert c.get("/api/volumes").json() == []
    r = c.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)})
    assert r.status_code == 201, r.text


# -- a 2 GB+ stream against a real server --------------------------------------------------


def memory(pid: int) -> dict[str, int]:
    """VmRSS and VmHWM of a process, bytes."""
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        key = line.split(":")[0]
        if key in ("VmRSS", "VmHWM"):
            out[key] = int(line.split()[1]) * 1024
    return out


def stream_upload(port: int, token: str, total: int, declare: bool) -> tuple[int, int, str]:
    """POST a multipart upload of ``total`` zero bytes over a raw socket, a megabyte at a
    time, stopping as soon as the server answers. Returns (bytes of the file sent,
    status, body). ``declare``: send Content-Length, else chunked transfer encoding."""
    head = b'--bnd7\r\nContent-Disposition: form-data; name="file"; filename="zeros.nii"\r\n\r\n'
    tail = b"\r\n--bnd7--\r\n"
    lines = [b"POST /api/volumes HTTP/1.1", b"Host: 127.0.0.1:%d" % port,
             b"Authorization: Bearer " + token.encode(),
             b"Content-Type: multipart/form-data; boundary=bnd7",
             b"Content-Length: %d" % (len(head) + total + len(tail)) if declare
             else b"Transfer-Encoding: chunked"]  # fmt: skip
    zeros, sent = bytes(1 << 20), 0
    with socket.create_connection(("127.0.0.1", port), timeout=60) as sock:

        def send(data: bytes) -> None:
            sock.sendall(data if declare else b"%x\r\n%s\r\n" % (len(data), data))

        sock.sendall(b"\r\n".join(lines) + b"\r\n\r\n")
        try:
            send(head)
            while sent < total and not select.select([sock], [], [], 0)[0]:
                n = min(len(zeros), total - sent)
                send(zeros[:n])
                sent += n
        except (BrokenPipeError, ConnectionResetError):
            pass  # the server answered and closed: read its answer
        answer = b""
        while b"\r\n\r\n" not in answer or not answer.rstrip().endswith(b"}"):
            chunk = sock.recv(65536)
            if not chunk:
                break
            answer += chunk
    status = int(answer.split(b" ", 2)[1])
    return sent, status, answer.split(b"\r\n\r\n", 1)[1].decode()


@pytest.fixture
def real_server(tmp_path: Path) -> Iterator[Any]:
    """``real_server(**env)``: ``miss serve`` (no demo, the server's own workers and limits
    but ``env``), logged in as admin; stopped after the test."""
    servers: list[Server] = []

    def start(**env: str) -> Server:
        n = len(servers)
        data, log = tmp_path / f"data{n}", tmp_path / f"serve{n}.log"
        server = Server(data, log, workers=None, env={"MISS_DEMO": "0", **env})
        servers.append(server)
        return server

    yield start
    for server in servers:
        if server.proc.poll() is None:
            server.stop(signal.SIGTERM)


TWO_GB = 2_200_000_000


@pytest.mark.processes  # a real ``miss serve``, 2.2 GB through the loopback
@pytest.mark.slow
@pytest.mark.parametrize(
    ("limit_mb", "declare"),
    [(None, True), ("16", False)],
    ids=["default-limit-declared-2.2GB", "16MB-limit-chunked-2.2GB"],
)
def test_two_gigabyte_stream_is_refused_early(
    real_server: Any, limit_mb: str | None, declare: bool
) -> None:
    """2.2 GB of zeros offered to a real ``miss serve``: the 413 arrives after at most the
    limit (plus socket buffers), not after the body; the server's memory does not grow by
    the body; no temp file remains and a good request works afterwards."""
    server = real_server(**({"MISS_MAX_UPLOAD_MB": limit_mb} if limit_mb else {}))
    limit = int(float(limit_mb or 2048) * 2**20)
    Path(f"/proc/{server.proc.pid}/clear_refs").write_text("5")  # restart the peak (VmHWM)
    before = memory(server.proc.pid)["VmRSS"]
    sent, status, body = stream_upload(server.port, server.token, TWO_GB, declare)
    assert status == 413, body
    detail = json.loads(body)["detail"]
    assert "MISS_MAX_UPLOAD_MB" in detail and "larger than the limit" in detail
    early = 64 << 20 if declare else limit + (64 << 20)  # declared: refused on the header
    assert sent <= early < TWO_GB, f"the 413 came after {sent} bytes"
    grown = memory(server.proc.pid)["VmHWM"] - before
    assert grown < 256 << 20, f"server peak memory grew by {grown / 2**20:.0f} MB"
    assert list((server.data_dir / "tmp").iterdir()) == []
    auth = {"Authorization": f"Bearer {server.token}"}
    assert server.http.get("/api/volumes", headers=auth).json() == []


# -- the bad-file corpus through the upload API --------------------------------------------

#: The server's one rule beyond the readers: a volume of one value is refused at the door
#: (no level can ever give a surface in it), where ``load_volume`` accepts it.
CONSTANT = "there is no surface to draw in it"


@pytest.mark.slow
def test_corpus_through_the_upload_api(
    site: Site, tmp_path_factory: pytest.TempPathFactory
) -> None:
    root = tmp_path_factory.mktemp("corpus")
    cases = generate(root / "cases")
    assert len(cases) > 50
    zips = root / "zips"
    zips.mkdir()
    failures = []
    for case in cases:
        path = as_upload(Path(case.path), root / "cases", zips)
        try:
            r = site.c.post("/api/volumes", files={"file": (path.name, path.read_bytes())})
            if r.status_code == 409 and case.expect == "ok":  # several series: the largest
                largest = r.json()["series"][0]["uid"]
                files = {"file": (path.name, path.read_bytes())}
                r = site.c.post("/api/volumes", files=files, data={"series": largest})
            if r.status_code == 201:  # gone again at once, right or wrong, for the next case
                assert site.c.delete(f"/api/volumes/{r.json()['id']}").status_code == 204
            if case.expect == "error" or (r.status_code == 422 and CONSTANT in r.text):
                refused(r)
                site.unchanged()
            else:
                assert r.status_code == 201, f"expected 201, got {r.status_code} {r.text[:300]}"
        except Exception as exc:  # noqa: BLE001 - one list of every case that went wrong
            failures.append(f"{case.name} ({case.expect}: {case.why}): {exc!r}"[:600])
    assert not failures, f"{len(failures)} of {len(cases)} cases:\n" + "\n".join(failures)
    site.unchanged()
