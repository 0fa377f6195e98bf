"""``import miss`` is cheap: the heavy libraries load on first use, and the documented
functions keep their names (``miss.decimate`` and ``miss.export`` are functions)."""

from __future__ import annotations

import json
import subprocess
import sys

HEAVY = ["vtk", "numba", "meshoptimizer", "pydicom", "SimpleITK", "nibabel", "scipy"]


def _modules_after(code: str) -> dict[str, bool]:
    probe = f"import sys\n{code}\nimport json\nprint(json.dumps({{m: m in sys.modules for m in {HEAVY!r}}}))"
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def test_import_miss_loads_no_heavy_library() -> None:
    assert _modules_after("import miss") == dict.fromkeys(HEAVY, False)


def test_the_cli_parser_loads_no_heavy_library() -> None:
    loaded = _modules_after("from miss.cli import build_parser; build_parser()")
    assert loaded == dict.fromkeys(HEAVY, False)


def test_colour_tables_load_without_the_scene_builder() -> None:
    """The confined reader of a label-map upload reads its colour table only."""
    assert _modules_after("import miss.structures.labels") == dict.fromkeys(HEAVY, False)


def test_documented_names_are_the_functions_after_their_modules_load() -> None:
    import miss
    import miss.decimate.quadric
    import miss.export.gltf
    import miss.structures.build  # noqa: F401

    assert callable(miss.decimate) and miss.decimate.__name__ == "decimate"
    assert callable(miss.export) and miss.export.__name__ == "export"
    assert miss.extract_scene.__module__ == "miss.structures.build"
    assert miss.Volume.__module__ == "miss.types"
