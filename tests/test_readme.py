"""The README stays a newcomer's document that tells the truth (issue 40).

It is short (at most 700 lines; the dated benchmark logs live in ``benchmarks/HISTORY.md``),
its Settings table names every setting the server reads with its default, its command
block names every command, and every relative link in it and in the pages it links to
(``docs/``, ``benchmarks/``) leads to a file and a heading that exist.
"""

from __future__ import annotations

import dataclasses
import importlib
import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
PAGES = [README, *sorted((ROOT / "docs").glob("*.md")), ROOT / "benchmarks" / "HISTORY.md"]
MAX_LINES = 700

_LINK = re.compile(r"\]\(([^)\s]+)\)")
_HEADING = re.compile(r"^#{1,6} +(.*?) *$", re.MULTILINE)
_ANCHOR_ID = re.compile(r'<a id="([^"]+)"')


def _section(text: str, title: str) -> str:
    """The text under the ``## title`` heading, up to the next ``## `` heading."""
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end > 0 else len(text)]


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to '-'."""
    text = re.sub(r"[`*_]|\[([^\]]*)\]\([^)]*\)", r"\1", heading).strip().lower()
    kept = "".join(c for c in text if c in " -" or unicodedata.category(c)[0] in "LN")
    return kept.replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    text = page.read_text(encoding="utf-8")
    text = re.sub(r"```.*?```", "", text, flags=re.DOTALL)  # '# comment' lines in code
    return {_slug(h) for h in _HEADING.findall(text)} | set(_ANCHOR_ID.findall(text))


def _settings_module():
    """The module that declares ``Settings`` and its environment names, wherever it lives."""
    for path in sorted((ROOT / "src" / "miss").rglob("settings.py")):
        name = ".".join(path.relative_to(ROOT / "src").with_suffix("").parts)
        module = importlib.import_module(name)
        if hasattr(module, "Settings") and hasattr(module, "_ENV"):
            return module
    raise AssertionError("no settings.py in src/miss declares Settings and _ENV")


def test_readme_is_short() -> None:
    lines = README.read_text(encoding="utf-8").count("\n")
    assert lines <= MAX_LINES, (
        f"README.md has {lines} lines, over {MAX_LINES}: move detail to docs/ and dated "
        "measurements to benchmarks/HISTORY.md"
    )


def test_settings_table_names_every_setting_with_its_default() -> None:
    module = _settings_module()
    table = _section(README.read_text(encoding="utf-8"), "Settings")
    rows = [line for line in table.splitlines() if line.startswith("| `MISS_")]
    defaults = {f.name: f.default for f in dataclasses.fields(module.Settings)}
    for field_name, env, _ in module._ENV:
        row = next((r for r in rows if f"`{env}`" in r), None)
        assert row is not None, f"{env} is missing from the README's Settings table"
        default = defaults[field_name]
        if isinstance(default, bool) or not isinstance(default, int | float) or default <= 0:
            continue  # derived or empty defaults are described in words
        number = int(default) if float(default).is_integer() else default
        spelled = {str(number), f"{number:,}"}
        assert any(re.search(rf"(?<![\d.,]){re.escape(s)}(?![\d,]|\.\d)", row) for s in spelled), (
            f"{env}: the README's row does not give the default {number}: {row}"
        )


def test_command_block_names_every_command() -> None:
    from miss.cli import COMMANDS

    block = _section(README.read_text(encoding="utf-8"), "Command line")
    for name in COMMANDS:
        assert re.search(rf"^miss(?: \S+ \|)? {re.escape(name)}\b", block, re.MULTILINE) or (
            f"miss {name} " in block
        ), f"`miss {name}` is missing from the README's command block"


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path) -> None:
    text = re.sub(r"```.*?```", "", page.read_text(encoding="utf-8"), flags=re.DOTALL)
    for target in _LINK.findall(text):
        if re.match(r"[a-z]+:", target):
            continue  # http:, https:, mailto:
        path, _, anchor = target.partition("#")
        linked = (page.parent / path).resolve() if path else page
        assert linked.is_file(), f"{page.name}: link to {target}: no such file"
        if anchor and linked.suffix == ".md":
            assert anchor in _anchors(linked), f"{page.name}: link to {target}: no such heading"
