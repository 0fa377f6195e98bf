"""Shared fixtures: the real scans in ../shared/datasets, skipped with a reason when absent;
the server fixtures (``support.server_app``) for every folder; the markers, set by folder."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from support import DATASETS
from support.pg import ENGINE

from miss.scene import Scene
from miss.types import Mesh

pytest_plugins = ["support.server_app"]

#: Markers by where a test lives (a folder, or a file of tests/ or tests/server/).
#: The fast lane, ``pytest -m "not slow"``, leaves out everything marked slow here or by
#: an explicit ``@pytest.mark.slow`` (a test over about 3 s on a 2-core machine).
MARKS_BY_PLACE = {
    "browser/": ("browser", "slow"),
    "pacs/": ("pacs", "slow"),
    # real ``miss serve`` or worker processes, killed, restarted or starved
    "server/test_processes.py": ("processes", "postgres", "slow"),
    "server/test_restart.py": ("processes", "slow"),
    "server/test_faults.py": ("processes", "slow"),
    "server/test_upload_streamed.py": ("processes", "slow"),
    "test_blocks_cluster.py": ("processes", "slow"),  # local Dask clusters
    "test_bench.py": ("slow",),  # the benchmarks' own code, run small
    "test_vrml_castle.py": ("slow",),  # Castle Game Engine's reader, a process per scene
}
#: Attack tests whose file starts a real server for (nearly) every test.
MARKS_BY_PLACE |= {
    f"security/test_{name}.py": ("processes", "slow")
    for name in [
        "access",
        "account_changes",
        "attack_corpus",
        "connection_limits",
        "deid_attacks",
        "deid_spellings",
        "fairness",
        "file_attacks",
        "file_modes",
        "guest_errors",
        "headers",
        "pacs_safety",
        "proxy_and_passwords",
        "room_limits",
    ]
}


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Mark each test by its place (``MARKS_BY_PLACE``); on a PostgreSQL run
    (``MISS_TEST_DATABASE=postgres``), every test ``postgres`` too."""
    tests = Path(__file__).parent
    for item in items:
        place = item.path.relative_to(tests).as_posix()
        names = [m for key, marks in MARKS_BY_PLACE.items() if place.startswith(key) for m in marks]
        if ENGINE == "postgres":
            names.append("postgres")
        for name in dict.fromkeys(names):
            item.add_marker(name)


@pytest.fixture(scope="session")
def datasets() -> Path:
    """Folder of real CT/MR scans; tests that need it skip when it is not beside the repo."""
    if not (DATASETS / "README.md").is_file():
        pytest.skip(f"real scans not found at {DATASETS} (clone ../shared beside the repo)")
    return DATASETS


@pytest.fixture(scope="session")
def real_scenes(datasets: Path) -> dict[str, Scene]:
    """The real-scan scenes every format's reference reader is tried on, built once:
    CThead's bone at 1500 undecimated and decimated (the server's defaults), and the frog's
    label map, all labels at sample rate 2. Errors are not measured (no test reads them)."""
    from miss.io import load_volume
    from miss.pipeline import run
    from miss.spec import JobSpec

    cthead = load_volume(datasets / "ct_head_stanford_cthead" / "CThead.nhdr")
    frog = load_volume(datasets / "labels_frogtissue" / "frogtissue.mhd")
    jobs = {
        "cthead-bone": (cthead, JobSpec.of(level=1500, decimate="none")),
        "cthead-bone-decimated": (cthead, JobSpec.of(level=1500)),
        "frog-labels": (frog, JobSpec.of(labels="all", sample_rate=2)),
    }
    return {name: run(v, spec, measure=False).scene for name, (v, spec) in jobs.items()}


@pytest.fixture(scope="session")
def browser() -> Iterator[Any]:
    """Debian's chromium through Playwright, one for the whole run: Playwright's sync API
    allows one driver at a time in a process (tests/browser/ and tests/pacs/ share it)."""
    from browser.conftest import CHROMIUM, CHROMIUM_ARGS, sync_api  # skips without them

    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield browser
        browser.close()


@pytest.fixture(scope="session")
def demo_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The synthetic CT head phantom written by ``miss demo`` as NIfTI (skin -500, bone 300 HU)."""
    path = tmp_path_factory.mktemp("demo") / "head.nii.gz"
    subprocess.run([sys.executable, "-m", "miss.cli", "demo", str(path)], check=True, timeout=300)
    return path


@pytest.fixture
def degenerate_mesh() -> Mesh:
    """A fan with a zero-area triangle, a vertex only it uses, and a vertex no triangle uses."""
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0], [9, 9, 9]], float)
    return Mesh(v, np.array([[0, 1, 2], [0, 1, 3], [1, 4, 3]]))
