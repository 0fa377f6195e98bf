"""A scene: several named, coloured surfaces shown together (skin over bone, organs).

A ``Part`` is one structure: a closed ``Mesh`` in LPS millimetres with a name, an
sRGB colour and an opacity, and the label it came from when it came from a label
map. A ``Scene`` is an ordered tuple of parts with a title; every writer in
:mod:`miss.export` accepts one in place of a mesh.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from miss.errors import BadParameter
from miss.geometry import enclosed_volume, surface_area
from miss.types import Mesh

RGB = tuple[float, float, float]

DEFAULT_SCENE_TITLE = "MISS scene"


@dataclass(frozen=True, eq=False)
class Part:
    """One named structure of a scene.

    Attributes
    ----------
    name : str
        Shown in viewers and used (made safe) as the node name in every format.
    mesh : Mesh
        Vertices (N, 3) in LPS mm, faces (F, 3) counter-clockwise from outside.
    color : (r, g, b)
        sRGB fractions in [0, 1].
    opacity : float
        In (0, 1]; 1 is opaque. Writers turn it into transparency or alpha blending.
    label : int or None
        The label-map value the part was built from; None for threshold surfaces.
    smoothed_mm : (float, float) or None
        How far smoothing moved the surface: its vertices' largest and mean displacement
        in mm (exact, before decimation); None when the part was not smoothed.
    """

    name: str
    mesh: Mesh
    color: RGB = (0.8, 0.8, 0.8)
    opacity: float = 1.0
    label: int | None = None
    smoothed_mm: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        if not str(self.name).strip():
            raise BadParameter("a part needs a non-empty name.")
        rgb = tuple(float(c) for c in self.color)
        if len(rgb) != 3 or not all(0.0 <= c <= 1.0 for c in rgb):
            raise BadParameter(
                f"part {self.name!r}: colour must be three fractions in [0, 1], got {self.color!r}."
            )
        if not (isinstance(self.opacity, int | float) and 0.0 < self.opacity <= 1.0):
            raise BadParameter(
                f"part {self.name!r}: opacity must be in (0, 1] (1 = opaque), got {self.opacity!r}."
            )
        object.__setattr__(self, "color", rgb)
        object.__setattr__(self, "opacity", float(self.opacity))

    @cached_property  # a part never changes; the writers and the stats all ask
    def volume_ml(self) -> float:
        """Enclosed volume in millilitres (cm³); meaningful for a closed surface."""
        return enclosed_volume(self.mesh.vertices, self.mesh.faces) / 1000.0

    @cached_property
    def area_cm2(self) -> float:
        """Surface area in cm²."""
        return surface_area(self.mesh.vertices, self.mesh.faces) / 100.0

    def summary(self) -> dict[str, Any]:
        """JSON-ready description: name, label, colour, opacity, triangles, mL, cm², and how
        far smoothing moved it (mm) when it was smoothed."""
        return {
            "name": self.name,
            "label": self.label,
            "color": [round(c, 4) for c in self.color],
            "opacity": round(self.opacity, 4),
            "triangles": self.mesh.n_triangles,
            "vertices": self.mesh.n_vertices,
            "volume_ml": round(self.volume_ml, 4),
            "area_cm2": round(self.area_cm2, 4),
            **(
                {}
                if self.smoothed_mm is None
                else {
                    "smoothing_max_mm": round(self.smoothed_mm[0], 4),
                    "smoothing_mean_mm": round(self.smoothed_mm[1], 4),
                }  # fmt: skip
            ),
        }


@dataclass(frozen=True, eq=False)
class Scene:
    """Parts shown together, in order (largest first when MISS builds them).

    Attributes
    ----------
    parts : tuple of Part
    title : str
    notes : tuple of str
        What building the scene had to drop or warn about, in plain words.
    """

    parts: tuple[Part, ...]
    title: str = DEFAULT_SCENE_TITLE
    notes: tuple[str, ...] = field(default=())

    def __post_init__(self) -> None:
        object.__setattr__(self, "parts", tuple(self.parts))
        object.__setattr__(self, "notes", tuple(self.notes))
        if any(not isinstance(p, Part) for p in self.parts):
            raise BadParameter("a scene holds Part objects only.")

    @property
    def n_triangles(self) -> int:
        """Triangles over all parts."""
        return sum(p.mesh.n_triangles for p in self.parts)

    @property
    def n_vertices(self) -> int:
        """Vertices over all parts."""
        return sum(p.mesh.n_vertices for p in self.parts)

    def bounds(self) -> np.ndarray:
        """(2, 3) array: min and max corner over all parts, mm."""
        boxes = [p.mesh.bounds() for p in self.parts if p.mesh.n_vertices]
        if not boxes:
            return np.zeros((2, 3))
        return np.stack([np.min([b[0] for b in boxes], 0), np.max([b[1] for b in boxes], 0)])

    def diagonal(self) -> float:
        """Length of the scene's bounding-box diagonal in mm."""
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))

    def merged(self) -> Mesh:
        """All parts as one mesh; ``labels`` (F,) holds each face's part index."""
        offsets = np.cumsum([0] + [p.mesh.n_vertices for p in self.parts])
        return Mesh(
            vertices=np.concatenate([p.mesh.vertices for p in self.parts]).astype(np.float32),
            faces=np.concatenate(
                [p.mesh.faces + int(o) for p, o in zip(self.parts, offsets, strict=False)]
            ).astype(np.int32),
            labels=np.repeat(np.arange(len(self.parts)), [p.mesh.n_triangles for p in self.parts]),
        )

    def summary(self) -> list[dict[str, Any]]:
        """One :meth:`Part.summary` per part, in order."""
        return [p.summary() for p in self.parts]


def safe_names(parts: tuple[Part, ...] | list[Part], *, style: str = "identifier") -> list[str]:
    """Unique names usable as node ids (VRML DEF, XML id) or file names, in part order.

    ``style="identifier"`` keeps letters, digits and ``_`` and never starts with a
    digit (VRML97 and XML ids forbid it); ``style="file"`` also keeps ``-`` and
    ``.``. Clashes get ``_2``, ``_3`` ... appended.
    """
    keep = "_" if style == "identifier" else "_-."
    out: list[str] = []
    for part in parts:
        base = "".join(c if c.isascii() and (c.isalnum() or c in keep) else "_" for c in part.name)
        base = re.sub("_+", "_", base).strip("_") or "part"
        if style == "identifier" and base[0].isdigit():
            base = "_" + base
        name, n = base, 2
        while name in out:
            name, n = f"{base}_{n}", n + 1
        out.append(name)
    return out


def linear_rgb(color: RGB) -> list[float]:
    """sRGB fractions to linear light (glTF's base colour factors are linear)."""
    return [
        round(c / 12.92 if c <= 0.04045 else math.pow((c + 0.055) / 1.055, 2.4), 4) for c in color
    ]
