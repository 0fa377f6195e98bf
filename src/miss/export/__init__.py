"""Surface meshes to bytes: one module per output format, registered in ``WRITERS``.

Every writer has the signature ``write(mesh, *, title=None, metadata=None,
**options) -> bytes`` and never touches the file system; adding a format is one
module and one line below. ``metadata`` is provenance (parameters, software
version, source hash) as strings; each format stores it where its readers look.

MIME types are the IANA-registered ones (``model/vrml``, ``model/x3d+xml``,
``model/gltf-binary``, ``model/stl``, ``model/obj``). PLY has no registration;
``model/ply`` follows the registered siblings and is what desktop tools and web
servers commonly send (``application/ply`` is rarely seen).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from miss.errors import BadParameter, EmptySurface, UnsupportedFormat
from miss.export import _zip, gltf, obj, ply, stl, vrml, x3d
from miss.scene import Scene
from miss.types import Mesh


@dataclass(frozen=True)
class Writer:
    """One output format.

    Attributes
    ----------
    write : callable
        ``write(mesh, *, title=None, metadata=None, **options) -> bytes``.
    mime : str
        The Content-Type to serve it with.
    binary : bool
        False for text formats (UTF-8 / ASCII).
    description : str
        One line for menus and ``--help``.
    options : frozenset of str
        Keyword options ``write`` takes beyond title and metadata.
    legacy_mime : str or None
        An older Content-Type some clients still send in ``Accept``.
    """

    write: Callable[..., bytes]
    mime: str
    binary: bool
    description: str
    options: frozenset[str] = frozenset()
    legacy_mime: str | None = None


WRITERS: dict[str, Writer] = {
    "wrl": Writer(
        vrml.write,
        "model/vrml",
        False,
        "VRML 2.0, the 1998 MISS format",
        legacy_mime="x-world/x-vrml",
    ),
    "wrz": Writer(
        vrml.write_gzip, "model/vrml", True, "VRML 2.0, gzipped", legacy_mime="x-world/x-vrml"
    ),
    "x3d": Writer(x3d.write, "model/x3d+xml", False, "X3D 3.3 XML, VRML's successor"),
    "glb": Writer(
        gltf.write,
        "model/gltf-binary",
        True,
        "glTF 2.0 binary, for web viewers",
        frozenset({"compress"}),
    ),
    "stl": Writer(stl.write, "model/stl", True, "binary STL, for 3-D printing"),
    "ply": Writer(ply.write, "model/ply", True, "binary PLY with normals"),
    "obj": Writer(obj.write, "model/obj", False, "Wavefront OBJ with normals"),
}

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
        A :class:`~miss.scene.Scene` goes to the format's scene writer
        (``SCENE_WRITERS``): named, coloured parts; a zip for stl, ply and obj.
    fmt : str
        One of ``FORMATS``, with or without a dot, any case.
    title : str, optional
        A human-readable name for the model.
    metadata : dict of str to str, optional
        Provenance to embed (parameters, software version, source hash).
    **options
        Format-specific, e.g. ``compress=True`` for "glb".

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
    if isinstance(mesh, Scene):
        return _export_scene(mesh, fmt, title, metadata, options)
    _check(mesh)
    return chosen.write(mesh, title=title, metadata=metadata, **options)


def _check(mesh: Mesh) -> None:
    """Refuse what every format would write as garbage: no triangles, bad indices, NaN."""
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


#: Scene writers, same keys as ``WRITERS``. Formats that hold one uncoloured mesh
#: (stl, ply) or need a side file (obj + mtl) write a zip with a ``scene.json``.
SCENE_WRITERS: dict[str, Callable[..., bytes]] = {
    "wrl": vrml.write_scene,
    "wrz": vrml.write_scene_gzip,
    "x3d": x3d.write_scene,
    "glb": gltf.write_scene,
    "stl": stl.write_scene,
    "ply": ply.write_scene,
    "obj": obj.write_scene,
}

#: Formats whose scene is a zip rather than one file of the format.
ZIPPED_SCENES: frozenset[str] = frozenset({"stl", "ply", "obj"})


def scene_mime_type(fmt: str) -> str:
    """The Content-Type of a scene in ``fmt``: the format's own, or ``application/zip``."""
    key = fmt.strip().lstrip(".").lower()
    return _zip.MIME if key in ZIPPED_SCENES else writer(fmt).mime


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
    key = fmt.strip().lstrip(".").lower()
    return SCENE_WRITERS[key](scene, title=title, metadata=metadata, **options)
