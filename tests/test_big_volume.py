"""Big volumes in bounded memory (issue 41): a volume whose voxels exceed the memory
budget (``MISS_IN_MEMORY_MAX_MB``) is read plane by plane to a chunked array on disk and
meshed block by block without ``--chunks``, with the surface one pass makes; a gzipped
NIfTI is inflated as it is read, never whole (its reader's peak memory is measured)."""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from big_volume import cthead_planes, write_gz_nifti  # benchmarks/ (pyproject: pythonpath)
from test_blocks import FLOAT32_ROUNDING_MM, assert_same_surface

from miss import BadParameter, extract_surface
from miss.types import IN_MEMORY_ENV, memory_budget

CTHEAD = (256, 256, 113)
MB = 2**20


@pytest.fixture(scope="module")
def cthead_gz(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """CThead (14.8 MB of int16 voxels) as a plain gzipped NIfTI."""
    path = tmp_path_factory.mktemp("big") / "cthead.nii.gz"
    return write_gz_nifti(path, CTHEAD, cthead_planes(CTHEAD))


def test_the_budget_is_a_setting_in_megabytes(monkeypatch) -> None:
    monkeypatch.delenv(IN_MEMORY_ENV, raising=False)
    assert memory_budget() == 256 * MB
    monkeypatch.setenv(IN_MEMORY_ENV, "2.5")
    assert memory_budget() == int(2.5 * MB)
    monkeypatch.setenv(IN_MEMORY_ENV, "lots")
    with pytest.raises(BadParameter, match=f"{IN_MEMORY_ENV}.*'lots'"):
        memory_budget()


def test_a_volume_in_memory_over_the_budget_is_meshed_in_blocks(cthead_gz, monkeypatch) -> None:
    """A volume read whole (a format that does not stream, or given as an array) still
    goes block by block past the budget: one pass would need three times its voxels."""
    from miss.io import load_volume
    from miss.surface.blockwise import in_blocks

    volume = load_volume(cthead_gz)
    monkeypatch.delenv(IN_MEMORY_ENV, raising=False)
    assert not in_blocks(volume, None)
    monkeypatch.setenv(IN_MEMORY_ENV, "4")
    assert in_blocks(volume, None)


@pytest.mark.slow
def test_a_job_over_the_budget_reads_to_disk_and_makes_the_one_pass_surface(
    cthead_gz, monkeypatch
) -> None:
    from miss.io import load_volume
    from miss.pipeline import run
    from miss.spec import FileSource, JobSpec

    monkeypatch.setenv(IN_MEMORY_ENV, "4")  # CThead's 14.8 MB are over it
    loaded = FileSource(str(cthead_gz)).load(labels=False)
    data = loaded.volume.data
    assert not isinstance(data, np.ndarray)  # on disk, read lazily
    folder = Path(data.folder).parent  # type: ignore[attr-defined]
    whole = load_volume(cthead_gz)
    assert loaded.volume.meta == whole.meta
    np.testing.assert_array_equal(loaded.volume.affine, whole.affine)
    np.testing.assert_array_equal(data[:, :, 60], whole.data[:, :, 60])

    got = run(loaded.volume, JobSpec.of(level=1500, decimate="none")).mesh
    want = extract_surface(whole, 1500.0, normals=False)
    assert_same_surface(got, want, FLOAT32_ROUNDING_MM)
    del loaded, data, got
    gc.collect()
    assert not folder.exists()  # the temporary array goes with the volume


@pytest.mark.slow
def test_miss_convert_over_the_budget_goes_block_by_block_without_a_flag(
    cthead_gz, tmp_path
) -> None:
    def convert(budget: str | None) -> dict:
        env = {k: v for k, v in os.environ.items() if k != IN_MEMORY_ENV}
        if budget is not None:
            env[IN_MEMORY_ENV] = budget
        proc = subprocess.run(
            [sys.executable, "-m", "miss.cli", "convert", str(cthead_gz), "--level", "1500",
             "-o", str(tmp_path / "bone.glb"), "--json"],
            capture_output=True, text=True, timeout=300, check=True, env=env,
        )  # fmt: skip
        return json.loads(proc.stdout)

    in_blocks, whole = convert("4"), convert(None)
    said = " ".join(in_blocks["notes"])
    assert "decimated in its blocks" in said
    assert "decimated in its blocks" not in " ".join(whole["notes"])
    before = whole["decimation"]["triangles_before"]
    assert in_blocks["decimation"]["triangles_before"] == before  # the same full surface
    assert in_blocks["decimation"]["bound_held"]


#: The child that reads a gzipped NIfTI over its budget, and reports its memory growth.
READER = textwrap.dedent(
    """
    import json, sys
    from pathlib import Path

    import numpy as np
    import zarr, numcodecs.blosc  # noqa: F401  (libraries loaded before the baseline)
    from miss.io.bounded import load_within
    from miss.server.storage import chunked  # noqa: F401

    def status(field):
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return int(line.split()[1]) * 1024

    Path("/proc/self/clear_refs").write_text("5")  # the high-water mark starts here
    base = status("VmRSS")
    volume = load_within(sys.argv[1], budget=64 << 20)
    grown = status("VmHWM") - base
    plane = volume.data[:, :, int(sys.argv[2])]
    print(json.dumps({"grown": grown, "lazy": not isinstance(volume.data, np.ndarray),
                      "shape": list(volume.data.shape), "sum": int(plane.astype(np.int64).sum())}))
    """
)


@pytest.mark.slow
def test_a_gzipped_nifti_is_inflated_slab_by_slab(tmp_path) -> None:
    """A 512 x 512 x 565 int16 .nii.gz (296 MB of voxels) read over a 64 MB budget: the
    reader's resident memory grows by far less than the voxels: 68 MB here (a layer of 64
    planes, 32 MB, and what zarr makes of it), where a whole read grows by 565 MB."""
    size = (512, 512, 565)
    path = write_gz_nifti(tmp_path / "big.nii.gz", size, cthead_planes(size))
    voxels = int(np.prod(size)) * 2
    proc = subprocess.run(
        [sys.executable, "-c", READER, str(path), "300"],
        capture_output=True, text=True, timeout=600, check=True,
    )  # fmt: skip
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert got["lazy"] and got["shape"] == list(size)
    want = next(p for k, p in enumerate(cthead_planes(size)) if k == 300)
    assert got["sum"] == int(want.astype(np.int64).sum())
    assert got["grown"] < voxels / 3, f"grew {got['grown'] / MB:.0f} MB"
