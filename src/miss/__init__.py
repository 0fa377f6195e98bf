"""MISS - Medical Image Sharing System.

The stable Python API::

    import miss
    vol = miss.load_volume(path, series=None)                      # -> Volume
    mesh = miss.extract_surface(vol, level, sample_rate=1, slices=None, roi=None)
    mesh, report = miss.decimate(mesh, method="quadric", reduce=0.9, error_bound=0.0002)
    data = miss.export(mesh, "wrl")                                # bytes
    scene = miss.extract_scene(vol, levels=[-500, 300])            # -> Scene (skin, bone)
    scene = miss.extract_scene(labelmap, labels="all")             # one part per label
    data = miss.export(scene, "glb")                               # named, coloured parts
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

# ``decimate`` and ``export`` are small front doors whose native libraries load on the
# first call, the names of ``_LAZY`` on first use: so every ``miss`` command starts quickly
# (it loads what its subcommand needs). A Python program's ``import miss`` then loads what
# the API's calls use (``_API_MODULES``), so that its first call does not pay for them.
from miss._process import as_command
from miss.decimate import DecimationReport, decimate
from miss.errors import BadParameter, EmptySurface, MissError, UnreadableVolume, UnsupportedFormat
from miss.export import WRITERS, export

if TYPE_CHECKING:
    from miss.io import load_volume
    from miss.scene import Part, Scene
    from miss.structures.build import extract_scene
    from miss.surface import extract_surface
    from miss.types import Mesh, Volume

#: Public names loaded on first use, and the module each comes from.
_LAZY = {
    "load_volume": "miss.io",
    "extract_surface": "miss.surface",
    "extract_scene": "miss.structures.build",
    "Part": "miss.scene",
    "Scene": "miss.scene",
    "Mesh": "miss.types",
    "Volume": "miss.types",
}


def __getattr__(name: str) -> Any:
    if name not in _LAZY:
        raise AttributeError(f"module 'miss' has no attribute {name!r}")
    value = getattr(importlib.import_module(_LAZY[name]), name)
    globals()[name] = value
    return value


#: What the API's calls load: the readers, VTK's filters, the simplifiers, the writers
#: (numba, pydicom, SimpleITK stay on first use: a few calls need them).
_API_MODULES = (
    "numpy",
    "meshoptimizer",
    "miss.io",
    "miss.surface",
    "miss.structures.build",
    "miss.decimate.quadric",
    "miss.decimate.schroeder",
    *(f"miss.export.{writer.module}" for writer in WRITERS.values()),
)
if not as_command():
    for _module in _API_MODULES:
        importlib.import_module(_module)

__version__ = "0.1.0"

__all__ = [
    "BadParameter",
    "DecimationReport",
    "EmptySurface",
    "Mesh",
    "MissError",
    "Part",
    "Scene",
    "UnreadableVolume",
    "UnsupportedFormat",
    "Volume",
    "__version__",
    "decimate",
    "export",
    "extract_scene",
    "extract_surface",
    "load_volume",
]
