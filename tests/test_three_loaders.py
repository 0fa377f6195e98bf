"""STL, PLY and OBJ files as the viewers read them: three.js's own loaders (STLLoader,
PLYLoader, OBJLoader from the npm package the web pages serve, run by node) and trimesh
read back exactly the triangles MISS wrote, degenerate ones included."""

from __future__ import annotations

import io
import json
import shutil
import subprocess
from pathlib import Path

import pytest
import trimesh

import miss
from miss.demo import phantom

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "tests" / "validators" / "load-three.mjs"
MODULES = REPO / "src" / "miss" / "web" / "node_modules"
FORMATS = ("stl", "ply", "obj")


def three_counts(fmt: str, paths: list[Path]) -> list[int]:
    node = shutil.which("node")
    if node is None or not (MODULES / "three").is_dir():
        pytest.skip("three.js from npm is not installed: run `make test` (npm, src/miss/web)")
    out = subprocess.run(
        [node, str(SCRIPT), str(MODULES), fmt, *map(str, paths)],
        capture_output=True, text=True, check=True, timeout=300,
    )  # fmt: skip
    return [json.loads(line)["triangles"] for line in out.stdout.splitlines()]


def meshes(datasets: Path | None, degenerate: miss.Mesh) -> dict[str, miss.Mesh | miss.Scene]:
    bone = miss.extract_surface(phantom(), 300.0, sample_rate=2)
    out: dict[str, miss.Mesh | miss.Scene] = {
        "phantom-bone": bone,
        "decimated": miss.decimate(bone, reduce=0.9, measure=False)[0],
        "degenerate": degenerate,
        # two parts in one file (a PLY's faces coloured by part, an OBJ's groups)
        "two-parts": miss.extract_scene(phantom(64, 3.0), levels=[-500, 300], measure=False),
    }
    if datasets is not None:
        cthead = miss.load_volume(datasets / "ct_head_stanford_cthead" / "CThead.nhdr")
        out["cthead-bone"] = miss.extract_surface(cthead, 1500.0)
    return out


@pytest.mark.parametrize("fmt", FORMATS)
@pytest.mark.slow
def test_three_and_trimesh_read_every_triangle(
    fmt: str, tmp_path: Path, request: pytest.FixtureRequest, degenerate_mesh: miss.Mesh
) -> None:
    try:
        datasets = request.getfixturevalue("datasets")
    except pytest.skip.Exception:
        datasets = None  # the synthetic meshes still run; the real scan needs ../shared
    found = meshes(datasets, degenerate_mesh)
    paths = []
    for name, mesh in found.items():
        paths.append(tmp_path / f"{name}.{fmt}")
        paths[-1].write_bytes(miss.export(mesh, fmt))
    counts = three_counts(fmt, paths)
    assert counts == [m.n_triangles for m in found.values()], (fmt, list(found))
    for path, mesh in zip(paths, found.values(), strict=True):
        loaded = trimesh.load(io.BytesIO(path.read_bytes()), file_type=fmt, process=False)
        assert len(loaded.faces) == mesh.n_triangles, (path.name, len(loaded.faces))
