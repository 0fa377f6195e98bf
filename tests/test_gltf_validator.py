"""Every GLB MISS writes passes the Khronos glTF-Validator (npm ``gltf-validator``, installed
by ``make test`` into tests/validators) with no error and no warning: one surface and
scenes, plain and meshopt-compressed (the validator cannot decode EXT_meshopt_compression,
so each compressed file's uncompressed twin is validated too), on the demo phantom, a mesh
with degenerate triangles, and the real scans (CThead bone, the frog's label map)."""

from __future__ import annotations

import json
import shutil
import subprocess
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import miss
from miss.demo import phantom
from miss.export import WRITERS
from miss.pipeline import run
from miss.scene import Scene
from miss.spec import JobSpec

VALIDATORS = Path(__file__).resolve().parent / "validators"
SCRIPT = VALIDATORS / "validate-gltf.mjs"

Validate = Callable[[dict[str, bytes]], dict[str, dict[str, Any]]]


@pytest.fixture(scope="module")
def validate(tmp_path_factory: pytest.TempPathFactory) -> Validate:
    """``validate({name: glb bytes})`` -> {name: the validator's issues}."""
    node = shutil.which("node")
    if node is None or not (VALIDATORS / "node_modules" / "gltf-validator").is_dir():
        pytest.skip("the glTF-Validator is not installed: run `make test` (npm, tests/validators)")
    folder = tmp_path_factory.mktemp("gltf")

    def check(files: dict[str, bytes]) -> dict[str, dict[str, Any]]:
        paths = {}
        for name, data in files.items():
            paths[name] = folder / f"{name}.glb"
            paths[name].write_bytes(data)
        out = subprocess.run(
            [node, str(SCRIPT), *map(str, paths.values())],
            capture_output=True, text=True, check=True, timeout=300, cwd=VALIDATORS,
        )  # fmt: skip
        reports = [json.loads(line) for line in out.stdout.splitlines()]
        by_path = {r["path"]: r["issues"] for r in reports}
        return {name: by_path[str(path)] for name, path in paths.items()}

    return check


def both(name: str, mesh_or_scene: miss.Mesh | Scene) -> dict[str, bytes]:
    """The GLB plain and meshopt-compressed, as the mesh or the scene writer makes it."""
    writer = WRITERS["glb"]
    write = writer.write_scene if isinstance(mesh_or_scene, Scene) else writer.write
    return {name: write(mesh_or_scene), f"{name}-compressed": write(mesh_or_scene, compress=True)}


def assert_valid(reports: dict[str, dict[str, Any]]) -> None:
    for name, issues in reports.items():
        bad = [m for m in issues["messages"] if m["severity"] <= 1]  # 0 error, 1 warning
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, (name, bad[:5])


def test_phantom_and_degenerate_meshes(validate: Validate, degenerate_mesh: miss.Mesh) -> None:
    volume = phantom()
    surface = miss.extract_surface(volume, 300.0, sample_rate=2)
    decimated = miss.decimate(surface, reduce=0.9, measure=False)[0]
    files = both("bone", surface) | both("bone-decimated", decimated)
    files |= both("degenerate", degenerate_mesh)
    zero = miss.Mesh(
        degenerate_mesh.vertices, degenerate_mesh.faces, normals=np.zeros((6, 3), np.float32)
    )
    files |= both("zero-normals", zero)
    assert_valid(validate(files))


def test_phantom_scenes_split_and_layered(validate: Validate) -> None:
    volume = phantom()
    split = run(volume, JobSpec.of(level=300, components="split", sample_rate=2, formats=("glb",)))
    layered = run(volume, JobSpec.of(levels=[-500, 300], sample_rate=2, formats=("glb",)))
    assert len(split.scene.parts) > 1 and len(layered.scene.parts) == 2
    files = both("split", split.scene) | both("layered", layered.scene)
    files["server"] = layered.artifacts["glb"]  # what the pipeline itself wrote
    assert_valid(validate(files))


@pytest.mark.slow
def test_real_scans(validate: Validate, real_scenes: dict[str, Scene]) -> None:
    assert len(real_scenes["frog-labels"].parts) > 20
    files: dict[str, bytes] = {}
    for name, scene in real_scenes.items():
        files |= both(name, scene)
    assert_valid(validate(files))
