"""Shared fixtures: the real scans in ../shared/datasets, skipped with a reason when absent."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from miss.types import Mesh

REPO = Path(__file__).resolve().parents[1]
DATASETS = Path(os.environ.get("MISS_DATASETS", REPO.parent / "shared" / "datasets"))


@pytest.fixture(scope="session")
def datasets() -> Path:
    """Folder of real CT/MR scans; tests that need it skip when it is not beside the repo."""
    if not (DATASETS / "README.md").is_file():
        pytest.skip(f"real scans not found at {DATASETS} (clone ../shared beside the repo)")
    return DATASETS


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
