"""Binary STL: the lingua franca of 3-D printing (implant models, surgical guides).

Layout (all little-endian): an 80-byte free header, a uint32 triangle count, then
one 50-byte record per triangle: float32 normal (3), float32 vertices (3 x 3),
uint16 attribute byte count (0). Coordinates stay in patient LPS millimetres,
which is what slicers for 3-D printers assume STL holds.
"""

from __future__ import annotations

import numpy as np

from miss.geometry import face_normals
from miss.scene import Scene
from miss.types import Mesh

# "<" everywhere: STL is little-endian whatever the host; packed, no padding.
_RECORD = np.dtype([("normal", "<f4", (3,)), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])
_COUNT = np.dtype("<u4")


def write(mesh: Mesh, *, title: str | None = None, metadata: dict[str, str] | None = None) -> bytes:
    """Encode ``mesh`` as binary STL.

    Parameters
    ----------
    mesh : Mesh
        Vertices (N, 3) in mm, faces (F, 3) counter-clockwise from outside (STL's
        right-hand rule: the facet normal points out).
    title, metadata
        The title goes into the 80-byte header (ASCII, cut to fit); metadata does
        not fit and is dropped.

    Returns
    -------
    bytes
        84 + 50 F bytes.
    """
    del metadata  # no room in the format
    records = np.zeros(mesh.n_triangles, dtype=_RECORD)
    records["vertices"] = mesh.vertices[mesh.faces]
    normals = face_normals(mesh.vertices, mesh.faces)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    # Degenerate triangles keep a zero normal; readers recompute it from the winding.
    records["normal"] = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    return _header(title) + np.array(mesh.n_triangles, dtype=_COUNT).tobytes() + records.tobytes()


def _header(title: str | None) -> bytes:
    """80 bytes that never start with b"solid" (readers would take the file for ASCII STL)."""
    text = f"MISS binary STL, mm, LPS: {title or 'surface'}"
    return text.encode("ascii", "replace")[:80].ljust(80, b"\0")


def write_scene(
    scene: Scene, *, title: str | None = None, metadata: dict[str, str] | None = None
) -> bytes:
    """One binary STL solid holding every part's triangles, in part order.

    STL has no parts nor colour (the attribute word's colour conventions contradict
    each other, so it stays 0): slicers and CAD tools read it as one solid; a scene's
    names and colours travel in the PLY, OBJ, glTF and 3MF files.
    """
    return write(scene.merged(), title=title or scene.title, metadata=metadata)
