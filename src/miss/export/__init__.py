"""Surface meshes to bytes: one module per output format, registered in ``WRITERS``.

Every format is one :class:`Writer` in ``WRITERS``: ``write(mesh, ...)`` for a plain
mesh and ``write_scene(scene, ...)`` for named, coloured parts (every MISS job is a
scene; a scene of one part in a one-mesh format is that format's plain file, a scene of
several one file that holds them all: STL one solid, PLY one mesh with faces coloured
by part, OBJ a group per part). Writers
take ``(…, *, title=None, metadata=None, **options)``, return bytes and never touch
the file system; adding a format is one module and one entry below. A mesh is in LPS
mm, its faces counter-clockwise seen from outside; normals are computed where the
mesh has none. ``metadata`` is provenance (parameters, software version, source hash)
as strings; each format stores it where its readers look.

MIME types are the IANA-registered ones (``model/vrml``, ``model/x3d+xml``,
``model/gltf-binary``, ``model/stl``, ``model/obj``, ``model/3mf``). PLY has no registration;
``model/ply`` follows the registered siblings and is what desktop tools and web
servers commonly send (``application/ply`` is rarely seen).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from miss.errors import BadParameter, EmptySurface, UnsupportedFormat

if TYPE_CHECKING:
    from miss.scene import Scene
    from miss.types import Mesh


@dataclass(frozen=True)
class Writer:
    """One output format.

    Attributes
    ----------
    module : str
        The module of ``miss.export`` that writes it (imported on first use, so that
        ``import miss`` stays cheap); it has ``write(mesh, *, title=None,
        metadata=None, **options) -> bytes`` and ``write_scene(scene, ...)``.
    mime : str
        The Content-Type to serve it with.
    binary : bool
        False for text formats (UTF-8 / ASCII).
    description : str
        One line for menus and ``--help``.
    options : frozenset of str
        Keyword options the writers take beyond title and metadata.
    legacy_mime : str or None
        An older Content-Type some clients still send in ``Accept``.
    one_mesh : bool
        The format's file is one mesh (stl, ply, obj): a scene of one part is written
        as that mesh; ``write_scene`` puts several parts in the one file.
    gzip : bool
        The writers' output gzipped (``.wrz``).
    label : str or None
        The Download button's text where ``.<format>`` would not say enough.
    """

    module: str
    mime: str
    binary: bool
    description: str
    options: frozenset[str] = frozenset()
    legacy_mime: str | None = None
    one_mesh: bool = False
    gzip: bool = False
    label: str | None = None

    @property
    def write(self) -> Callable[..., bytes]:
        """The format's ``write(mesh, ...) -> bytes``, imported when first asked for."""
        return self._function("write")

    @property
    def write_scene(self) -> Callable[..., bytes]:
        """The format's ``write_scene(scene, ...) -> bytes``, imported when first asked for."""
        return self._function("write_scene")

    def _function(self, name: str) -> Callable[..., bytes]:
        module = importlib.import_module(f"miss.export.{self.module}")
        return getattr(module, f"{name}_gzip" if self.gzip else name)


_VRML = "x-world/x-vrml"
WRITERS: dict[str, Writer] = {
    "wrl": Writer("vrml", "model/vrml", False, "VRML 2.0, the 1998 MISS format",
                  legacy_mime=_VRML),
    "wrz": Writer("vrml", "model/vrml", True, "VRML 2.0, gzipped", legacy_mime=_VRML,
                  gzip=True),
    "x3d": Writer("x3d", "model/x3d+xml", False, "X3D 3.3 XML, VRML's successor"),
    "glb": Writer("gltf", "model/gltf-binary", True, "glTF 2.0 binary, for web viewers",
                  frozenset({"compress", "ordered"})),
    # No extension required: float32 positions and normals, plain indices (the writers'
    # default); the server's .glb is meshopt-compressed, which many tools cannot read.
    "plain.glb": Writer("gltf", "model/gltf-binary", True,
                        "glTF 2.0 binary without extensions, parts named and coloured, "
                        "for tools that cannot read the compressed .glb",
                        label="GLB (plain, opens anywhere)"),
    "stl": Writer("stl", "model/stl", True, "binary STL, one solid, for 3-D printing",
                  one_mesh=True),
    "ply": Writer("ply", "model/ply", True, "binary PLY with normals, faces coloured by part",
                  one_mesh=True),
    "obj": Writer("obj", "model/obj", False, "Wavefront OBJ with normals, a group per part",
                  one_mesh=True),
    "3mf": Writer("threemf", "model/3mf", True, "3MF, each part in its colour, for 3-D printing"),
}  # fmt: skip

FORMATS: list[str] = list(WRITERS)


def writer(fmt: str) -> Writer:
    """The ``Writer`` for ``fmt``: an extension such as "wrl", ".wrl" or "WRL"."""
    key = fmt.strip().lstrip(".").lower()
    try:
        return WRITERS[key]
    except KeyError:
        known = ", ".join(FORMATS)
        raise UnsupportedFormat(f"Cannot export {fmt!r}: choose one of {known}.") from None


def mime_type(fmt: str) -> str:
    """The Content-Type for ``fmt`` ("wrl" -> "model/vrml")."""
    return writer(fmt).mime


def export(
    mesh: Mesh | Scene,
    fmt: str,
    *,
    title: str | None = None,
    metadata: dict[str, str] | None = None,
    **options: object,
) -> bytes:
    """Encode ``mesh`` in format ``fmt``.

    Parameters
    ----------
    mesh : Mesh or Scene
        Vertices (N, 3) in patient LPS mm, faces (F, 3) counter-clockwise from
        outside; normals are computed (area-weighted) when ``mesh.normals`` is None.
        A :class:`~miss.scene.Scene` goes to the format's scene writer: named,
        coloured parts; stl, ply and obj hold them in one file (one part: the plain
        file).
    fmt : str
        One of ``FORMATS``, with or without a dot, any case.
    title : str, optional
        A human-readable name for the model.
    metadata : dict of str to str, optional
        Provenance to embed (parameters, software version, source hash).
    **options
        Format-specific, e.g. ``compress=True`` for "glb" (and ``ordered=True`` when
        the scene is already in :func:`miss.geometry.locality_order`, as a job's is;
        "plain.glb" takes none: it is never compressed).

    Returns
    -------
    bytes
        The file's contents.
    """
    chosen = writer(fmt)
    unknown = set(options) - chosen.options
    if unknown:
        takes = ", ".join(sorted(chosen.options)) or "none"
        raise BadParameter(
            f"Format {fmt!r} has no option {', '.join(sorted(unknown))}; it takes: {takes}."
        )
    from miss.scene import Scene

    if isinstance(mesh, Scene):
        return _export_scene(mesh, fmt, title, metadata, options)
    _check(mesh)
    return chosen.write(mesh, title=title, metadata=metadata, **options)


def _check(mesh: Mesh) -> None:
    """Refuse what every format would write as garbage: no triangles, bad indices, NaN."""
    import numpy as np

    if mesh.n_triangles == 0:
        raise EmptySurface(
            "Nothing to export: the mesh has no triangles (try another level or region)."
        )
    if mesh.faces.ndim != 2 or mesh.faces.shape[1] != 3:
        raise ValueError(f"Mesh faces must be (F, 3) triangles, got shape {mesh.faces.shape}.")
    if mesh.faces.min() < 0 or mesh.faces.max() >= mesh.n_vertices:
        raise ValueError(f"Mesh faces index vertices outside 0..{mesh.n_vertices - 1}.")
    if not np.isfinite(mesh.vertices).all():
        raise ValueError("Mesh vertices contain NaN or infinity.")


def _export_scene(
    scene: Scene,
    fmt: str,
    title: str | None,
    metadata: dict[str, str] | None,
    options: dict[str, object],
) -> bytes:
    """Check every part as :func:`_check` does a mesh, then call the scene writer."""
    if not scene.parts:
        raise EmptySurface(
            "Nothing to export: the scene has no parts (try other levels or labels)."
        )
    for part in scene.parts:
        try:
            _check(part.mesh)
        except ValueError as exc:
            raise type(exc)(f"part {part.name!r}: {exc}") from exc
    chosen = writer(fmt)
    if chosen.one_mesh and len(scene.parts) == 1:
        return chosen.write(
            scene.parts[0].mesh, title=title or scene.parts[0].name, metadata=metadata
        )
    return chosen.write_scene(scene, title=title, metadata=metadata, **options)
