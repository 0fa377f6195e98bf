"""Structures: the named parts of a scene and what they are built from.

- :mod:`~miss.structures.build`: ``extract_scene`` / ``build_scene``, the parts a job
  asks for (iso-levels, their components, label maps), smoothed and decimated;
- :mod:`~miss.structures.components`: connected pieces of a level (largest, split);
- :mod:`~miss.structures.labelmap`: label maps, surface nets with shared boundaries;
- :mod:`~miss.structures.labels`: label names and colour tables (3D Slicer, ITK-SNAP,
  NIfTI header tables, TotalSegmentator).

Light to import (a confined upload reader needs only the colour tables): the scene
builder and its libraries load on first use.
"""

from __future__ import annotations

import importlib
from typing import Any

_BUILD = ("extract_scene", "build_scene", "combined_report", "level_style", "SceneBuild")


def __getattr__(name: str) -> Any:
    if name not in _BUILD:
        raise AttributeError(f"module 'miss.structures' has no attribute {name!r}")
    return getattr(importlib.import_module("miss.structures.build"), name)
