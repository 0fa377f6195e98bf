"""The model page names every module it imports in ``<link rel="modulepreload">``, so that
the browser fetches them all at once instead of one level of imports after another (the
first pixels after Generate wait for them). The list is checked against the imports."""

from __future__ import annotations

import json
import posixpath
import re
from pathlib import Path

import pytest

WEB = Path(__file__).resolve().parents[1] / "src/miss/web"
IMPORTS = re.compile(
    r"""(?:^|[;\s])(?:import|export)\s[^'";]*?from\s*['"]([^'"]+)['"]"""
    r"""|(?:^|[;\s])import\s*['"]([^'"]+)['"]""",
    re.MULTILINE,
)
BLOCK_COMMENTS = re.compile(r"/\*.*?\*/", re.DOTALL)
LINE_COMMENTS = re.compile(r"^\s*//.*$", re.MULTILINE)


def local(url: str) -> Path:
    """The file a page's URL serves (``/static/`` from the web folder, ``/vendor/three/``
    from the npm package)."""
    if url.startswith("/static/"):
        return WEB / url.removeprefix("/static/")
    if url.startswith("/vendor/three/"):
        return WEB / "node_modules/three" / url.removeprefix("/vendor/three/")
    raise AssertionError(f"{url} is served from neither /static/ nor /vendor/three/")


def resolve(spec: str, base: str, import_map: dict[str, str]) -> str:
    """An import's URL, as the browser resolves it with the page's import map."""
    for key, target in import_map.items():
        if spec == key or (key.endswith("/") and spec.startswith(key)):
            return target + spec.removeprefix(key)
    return posixpath.normpath(posixpath.join(posixpath.dirname(base), spec))


def module_graph(entry: str, import_map: dict[str, str]) -> list[str]:
    """Every module ``entry`` imports, directly or not, in the order they are found."""
    seen: list[str] = []
    todo = [entry]
    while todo:
        url = todo.pop(0)
        if url in seen:
            continue
        seen.append(url)
        text = local(url).read_text(encoding="utf-8")
        text = LINE_COMMENTS.sub("", BLOCK_COMMENTS.sub("", text))
        todo += [resolve(a or b, url, import_map) for a, b in IMPORTS.findall(text)]
    return seen[1:]


def page_import_map(html: str) -> dict[str, dict[str, str]]:
    """A page's import map, as its ``<script type="importmap">`` says."""
    return json.loads(re.search(r'<script type="importmap">(.*?)</script>', html, re.S)[1])


def test_model_page_preloads_exactly_the_modules_it_imports() -> None:
    if not (WEB / "node_modules/three").is_dir():
        pytest.skip("three.js is not installed in src/miss/web (make web-deps installs it)")
    html = (WEB / "model.html").read_text(encoding="utf-8")
    import_map = page_import_map(html)
    entry = re.search(r'<script type="module" src="([^"]+)"', html)[1]
    graph = module_graph(entry, import_map["imports"])
    preloaded = re.findall(r'<link rel="modulepreload" href="([^"]+)">', html)
    assert "/vendor/three/build/three.module.js" in graph  # the walk follows the import map
    assert sorted(preloaded) == sorted(graph), (
        f"missing: {sorted(set(graph) - set(preloaded))}; "
        f"not imported: {sorted(set(preloaded) - set(graph))}"
    )
    for url in preloaded:
        assert local(url).is_file(), url


def test_the_volume_page_resolves_modules_as_the_model_page_does() -> None:
    """Generate runs the model page's modules in the volume page's document
    (pages/volume-page.js): its import map must be the model page's, or three would be
    another file there than on the model's own page."""
    volume, model = (
        (WEB / name).read_text(encoding="utf-8") for name in ("volume.html", "model.html")
    )
    assert page_import_map(volume) == page_import_map(model)
