"""The native measurement (:mod:`miss.measure._native`) is numba's, to the bit: the same samples,
the same distances, the same figures, on random surfaces with degenerate triangles and on a
real scan's; and ``miss convert --measure`` measures with it, no numba anywhere."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_deviation import brute, pieces_mesh, probes

from miss.geometry import locality_order
from miss.measure import _jit as jitted
from miss.measure import _native as measuring
from miss.measure import surface_grid
from miss.measure._core import _median
from miss.types import Mesh


def test_the_native_kernels_are_built() -> None:
    """``make`` builds them (setup.py); the extension is optional, so a build that failed
    would otherwise pass unseen, every measurement falling back to numba's."""
    assert measuring.native(), "src/miss/measure/_nearest.cpp was not built: run `make test` again"


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    spread=st.sampled_from([0.0, 20.0, 1000.0]),
    broken=st.sampled_from([0.0, 0.3, 1.0]),
    dtype=st.sampled_from([np.float64, np.float32]),
)
def test_native_distances_are_numbas_and_exact(seed, spread, broken, dtype) -> None:
    mesh = pieces_mesh(seed, 4, spread, broken, dtype)
    points = probes(mesh, seed + 1, spread)
    grid = measuring.native_grid(mesh)
    got = measuring.distances(points, grid)
    np.testing.assert_array_equal(got, jitted.distances_to(points, mesh))
    np.testing.assert_array_equal(measuring.distances(points, grid, ordered=True), got)
    tol = 1e-9 if dtype == np.float64 else 1e-5
    scale = 1.0 + np.abs(points).max() + np.abs(mesh.vertices).max()
    np.testing.assert_allclose(got, brute(points, mesh.vertices, mesh.faces), atol=tol * scale)
    # capped: exact up to the cap, above it only known to be above
    capped = measuring.distances(points, grid, cap=5.0)
    np.testing.assert_array_equal(capped[got <= 5.0], got[got <= 5.0])
    assert np.all(capped[got > 5.0] > 5.0)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    dtype=st.sampled_from([np.float64, np.float32]),
    samples=st.sampled_from([10, 301, 2000]),
)
def test_native_figures_are_numbas_to_the_bit(seed, dtype, samples) -> None:
    a = pieces_mesh(seed, 3, 20.0, 0.2, dtype)
    b = pieces_mesh(seed + 1, 2, 20.0, 0.2, dtype)
    want = jitted.deviation(a, b, samples=samples, seed=5)
    assert measuring.native_deviation(a, b, samples=samples, seed=5) == want
    side = measuring.native_side_of(a, samples=samples, seed=5)
    np.testing.assert_array_equal(side.points, jitted.side_of(a, samples, seed=5).points)
    assert measuring.native_deviation(a, b, samples=samples, seed=5, side=side) == want
    # a half made natively, measured by numba's kernels (numba loaded in between)
    assert jitted.deviation(a, b, samples=samples, seed=5, side=side) == want


def test_either_search_takes_either_grid() -> None:
    mesh = pieces_mesh(1, 3, 20.0, 0.3, np.float32)
    points = probes(mesh, 2, 20.0)
    want = jitted.distances_to(points, mesh)
    np.testing.assert_array_equal(measuring.distances(points, jitted.jit_grid(mesh)), want)
    np.testing.assert_array_equal(
        jitted.distances_to(points, mesh, grid=measuring.native_grid(mesh)), want
    )
    # and the public entry's, whichever kernels it picks here
    grids = jitted.jit_grid(mesh), measuring.native_grid(mesh), surface_grid(mesh)
    for a, b, c in zip(*grids, strict=True):
        np.testing.assert_array_equal(a, b)
        np.testing.assert_array_equal(a, c)


@given(st.lists(st.floats(0.0, 1e3), min_size=1, max_size=40))
def test_the_grids_median_is_numpys(values) -> None:
    assert _median(np.array(values)) == float(np.median(values))


def test_empty_surfaces_measure_nothing() -> None:
    a = pieces_mesh(1, 2, 20.0, 0.0, np.float32)
    none = Mesh(vertices=a.vertices, faces=np.empty((0, 3), dtype=np.int32))
    assert measuring.native_deviation(a, none).samples == 0
    assert measuring.distances(np.empty((0, 3)), measuring.native_grid(a)).shape == (0,)


def test_a_real_scans_figures_are_numbas(datasets: Path) -> None:
    """CThead at a bone level against its quadric decimation to 10 %, 100,000 samples a
    side: the figures a job reports, native and numba's alike."""
    import miss

    volume = miss.load_volume(datasets / "ct_head_stanford_cthead" / "CThead.nhdr")
    before = miss.extract_surface(volume, 1500.0, normals=False)
    after, _ = miss.decimate(before, "quadric", 0.9, measure=False, schedule="paper")
    want = jitted.deviation(before, after)
    assert measuring.native_deviation(before, after) == want
    side = measuring.native_side_of(before)
    assert measuring.native_deviation(before, after, side=side) == want
    assert want.max_mm > 0 and want.samples == 200_000


_CONVERT = """
import json, sys
from miss.cli import main
main(["convert", {path!r}, "--level", "300", "--schedule", "paper", "--reduce", "0.9",
      "--measure", "--json", "-o", {out!r}])
from miss.measure import measurer
print(json.dumps({{"numba": "numba" in sys.modules, "children": len(measurer._SHARED)}}))
"""


def test_a_fresh_command_measures_natively_in_its_own_process(
    demo_file: Path, tmp_path: Path
) -> None:
    """``miss convert --measure`` (paper schedule): neither numba nor a measuring process
    is started, and the figures are numba's."""
    code = _CONVERT.format(path=str(demo_file), out=str(tmp_path / "m.glb"))
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=600, check=True
    )
    stats, seen = (json.loads(line) for line in proc.stdout.strip().splitlines()[-2:])
    assert seen == {"numba": False, "children": 0}
    import miss

    before = miss.extract_surface(miss.load_volume(demo_file), 300.0, normals=False)
    after, _ = miss.decimate(before, "quadric", 0.9, measure=False, schedule="paper")
    want = jitted.deviation(before, locality_order(after))  # as the job lays its scene out
    got = stats["decimation"]
    assert (got["max_error_mm"], got["mean_error_mm"]) == (want.max_mm, want.mean_mm)


def test_a_kernel_out_of_memory_raises_memory_error_not_an_abort() -> None:
    """A C++ exception must not cross into ctypes (the process would end): a kernel that
    cannot have its memory answers so, and Python raises MemoryError, which a job's
    measurement already takes (its half is made again, or the job fails cleanly)."""
    lib = measuring._library()
    far = 2**60  # past any vector's size: the first allocation fails, nothing is touched
    with pytest.raises(MemoryError):
        measuring._checked(lib.miss_increasing(None, far, 1.0, None))
    dims = np.array([1, 1, 1], dtype=np.int64)
    lo = np.zeros(3)
    with pytest.raises(MemoryError):
        measuring._checked(
            lib.miss_distances_f32(
                None,
                far,
                lo.ctypes.data,
                1.0,
                dims.ctypes.data,
                None,
                None,
                None,
                0.0,
                0,
                1,
                None,
            )  # fmt: skip
        )
