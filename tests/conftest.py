"""Shared fixtures: the real scans in ../shared/datasets, skipped with a reason when absent."""

from __future__ import annotations

import os
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
