"""The numba kernels (miss.decimate._quadric, used once numba is loaded) and their numpy versions (used
by a process that has not loaded it) give the same results, bit for bit."""

from __future__ import annotations

import importlib
import subprocess
import sys
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from miss.demo import phantom
from miss.surface import extract_surface
from miss.types import Mesh

surface = importlib.import_module("miss.surface")
quadric = importlib.import_module("miss.decimate.quadric")


def _both(monkeypatch: pytest.MonkeyPatch, run: Callable[[], Any]) -> tuple[Any, Any]:
    """``run()`` with numba loaded, and again as a process without numba sees it."""
    import numba  # noqa: F401

    compiled = run()
    with monkeypatch.context() as m:
        m.delitem(sys.modules, "numba")
        plain = run()
    return compiled, plain


def _assert_same(a: Any, b: Any) -> None:
    for x, y in zip(a, b, strict=True):
        assert x.dtype == y.dtype
        np.testing.assert_array_equal(x, y)


@pytest.fixture(scope="module")
def pieces() -> Mesh:
    """Bone and skin of the phantom as one mesh: pieces of every size."""
    volume = phantom(96, spacing=2.0)
    bone, skin = (extract_surface(volume, level, normals=False) for level in (300.0, -500.0))
    faces = np.concatenate([bone.faces, skin.faces + bone.n_vertices])
    return Mesh(np.concatenate([bone.vertices, skin.vertices]), faces)


@pytest.mark.parametrize("level", [300.0, -500.0])
def test_slab_welding(monkeypatch: pytest.MonkeyPatch, level: float) -> None:
    block = phantom(96, spacing=2.0).data
    contour = surface.contour_level(block.dtype, level)
    span = float(block.max() - block.min())
    monkeypatch.setattr(surface, "_SLAB_VOXELS", 96 * 96 * 16)
    assert len(surface._seam_planes(block, contour)) >= 3
    _assert_same(*_both(monkeypatch, lambda: surface._surface_in_slabs(block, contour, span)))


def test_roots_and_partition(monkeypatch: pytest.MonkeyPatch, pieces: Mesh) -> None:
    rng = np.random.default_rng(7)
    shuffled = rng.permutation(pieces.n_vertices)[pieces.faces].astype(np.int32)  # long chains
    for faces in (pieces.faces, shuffled):
        roots = _both(monkeypatch, lambda f=faces: (quadric._roots(f, pieces.n_vertices),))
        _assert_same(*roots)
        assert (roots[0][0] <= np.arange(pieces.n_vertices)).all()
    coord = np.ascontiguousarray(pieces.vertices[:, 1], dtype=np.float64)
    cuts = np.quantile(3 * coord[pieces.faces[:, 0]], np.linspace(0, 1, 17)[1:-1])
    faces = pieces.faces.view(np.uint32)
    _assert_same(*_both(monkeypatch, lambda: quadric._partition(faces, coord, cuts)))


def test_quadric(monkeypatch: pytest.MonkeyPatch, pieces: Mesh) -> None:
    monkeypatch.setattr(quadric, "_PARALLEL_MIN_TRIANGLES", 1000)  # the two-phase path too
    (faces_a, error_a), (faces_b, error_b) = _both(
        monkeypatch, lambda: quadric.quadric(pieces, 0.9, 0.01)
    )
    np.testing.assert_array_equal(faces_a, faces_b)
    assert error_a == error_b


def test_a_job_that_does_not_measure_loads_no_numba() -> None:
    code = (
        "import sys, miss\n"
        "from miss.demo import phantom\n"
        "mesh = miss.extract_surface(phantom(64, spacing=3.0), 300.0, normals=False)\n"
        "miss.decimate(mesh, 'quadric', 0.9, measure=False)\n"
        "print('numba' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


NUMBA_START = """
import sys
import numpy as np
from numba import njit
from miss.measure._jit import deviation
from miss.demo import phantom
from miss.surface import extract_surface

mesh = extract_surface(phantom(), 300.0, sample_rate=4)
assert deviation(mesh, mesh, samples=500).max_mm < 1e-3
print("scipy.linalg" in sys.modules)

@njit
def dot(a, b):
    return np.dot(a, b)

a = np.arange(6.0).reshape(2, 3)
print(np.array_equal(dot(a, a.T), a @ a.T))
"""


@pytest.mark.slow
def test_numba_starts_without_importing_scipy_for_a_blas_check() -> None:
    # MISS's kernels run in a fresh process without numba importing scipy.linalg (a BLAS
    # check they never need); a jitted np.dot still finds the BLAS when it is compiled
    done = subprocess.run(
        [sys.executable, "-c", NUMBA_START], capture_output=True, text=True, timeout=300
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.split() == ["False", "True"]
