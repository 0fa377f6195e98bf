"""The pages' files under versioned URLs (miss.server.core.assets): a browser keeps them a year
and asks again only for a new version; the plain URLs answer 304 to a copy it holds."""

from __future__ import annotations

import base64
import hashlib
import os
import re
import shutil
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from miss.server.core import assets
from miss.server.core.headers import import_map_hashes

URL = re.compile(r"""["'](/(?:v/[0-9a-f]+/)?(?:static|vendor)/[^"']+)["']""")


def test_a_page_names_its_files_under_the_current_version(client: TestClient) -> None:
    version = assets.version()
    for path in ("/", "/volumes/x", "/models/x", "/docs", "/redoc", "/login"):
        page = client.get(path)
        assert page.status_code == 200, path
        urls = URL.findall(page.text)
        assert urls, path
        assert all(u.startswith(f"/v/{version}/") for u in urls), (path, urls)
        assert page.headers["cache-control"] == "no-cache"
        # the import map as sent is the one the policy allows (else the browser refuses it)
        sources = import_map_hashes(page.text)
        csp = page.headers["content-security-policy"]
        assert all(s in csp.split("script-src")[1].split(";")[0] for s in sources), path
    assert "'unsafe-inline'" in client.get("/redoc").headers["content-security-policy"]
    assert "'unsafe-inline'" not in client.get("/docs").headers["content-security-policy"]
    model = client.get("/models/x").text
    block = re.search(r'<script type="importmap">(.*?)</script>', model, re.S).group(1)
    digest = hashlib.sha256(block.encode()).digest()
    assert import_map_hashes(model) == [f"'sha256-{base64.b64encode(digest).decode()}'"]
    assert f"/v/{version}/vendor/three/build/three.module.js" in model


def test_a_versioned_file_is_kept_a_year_and_an_old_version_is_not(client: TestClient) -> None:
    version = assets.version()
    plain = client.get("/static/js/api.js")
    kept = client.get(f"/v/{version}/static/js/api.js")
    assert kept.status_code == plain.status_code == 200
    assert kept.content == plain.content
    assert kept.headers["cache-control"] == "public, max-age=31536000, immutable"
    assert kept.headers["content-type"].startswith("text/javascript")
    assert plain.headers["cache-control"] == "no-cache"
    # a page sent before an edit asks under its version: the file as it is now, not kept
    old = client.get("/v/000000000000/static/js/api.js")
    assert old.status_code == 200 and old.content == plain.content
    assert old.headers["cache-control"] == "no-cache"
    if (assets.MODULES / "three").is_dir():
        three = client.get(f"/v/{version}/vendor/three/build/three.module.js")
        assert three.status_code == 200 and "immutable" in three.headers["cache-control"]
    # the same rules as the plain URLs: nothing outside the folders
    assert client.get(f"/v/{version}/static/../server/app.py").status_code == 404
    assert client.get(f"/v/{version}/static/node_modules/three/package.json").status_code == 404
    assert client.get(f"/v/{version}/vendor/nothing/x.js").status_code == 404


def test_a_copy_the_browser_holds_is_answered_304(client: TestClient) -> None:
    for url in ("/static/js/api.js", f"/v/{assets.version()}/static/js/api.js"):
        first = client.get(url)
        etag = first.headers["etag"]
        again = client.get(url, headers={"If-None-Match": etag})
        assert again.status_code == 304 and again.content == b"", url
        assert again.headers["etag"] == etag
        assert again.headers["cache-control"] == first.headers["cache-control"]
        listed = client.get(url, headers={"If-None-Match": f'"other", W/{etag}'})
        assert listed.status_code == 304
        other = client.get(url, headers={"If-None-Match": '"other"'})
        assert other.status_code == 200 and other.content == first.content


def test_an_edited_file_makes_a_new_version(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    web = tmp_path / "web"
    shutil.copytree(assets.WEB, web, ignore=shutil.ignore_patterns("node_modules"))
    monkeypatch.setattr(assets, "WEB", web)
    monkeypatch.setattr(assets, "MODULES", web / "node_modules")
    first = assets.version()
    assert first == assets.version() and re.fullmatch(r"[0-9a-f]{12}", first)
    module = web / "js" / "api.js"
    stat = module.stat()
    os.utime(module, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    edited = assets.version()
    assert edited != first
    (web / "js" / "new.js").write_text("export const x = 1;\n")
    assert assets.version() not in (first, edited)
