"""Shared fixtures: the real scans in ../shared/datasets, skipped with a reason when absent."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

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
