"""glTF 2.0 binary (``.glb``): what today's browsers (three.js, model-viewer) load.

Frame and units. glTF is metres, right-handed, +Y up, and an asset's front faces
+Z. MISS data is patient LPS millimetres (+x left, +y posterior, +z superior).
The buffer keeps the millimetres untouched; the root node's matrix does both
changes at once, ``FRAME = 0.001 * R`` with

    glTF +X = patient left       (LPS +x)
    glTF +Y = superior, "up"     (LPS +z)
    glTF +Z = anterior           (LPS -y)

Check of handedness: in LPS coordinates left x superior = (1,0,0) x (0,0,1) =
(0,-1,0) = anterior, so X x Y = Z and ``det R = +1``: a proper rotation (-90
degrees about x), no mirror, triangle winding and normals survive unchanged. The
patient faces +Z, glTF's "front", and a viewer in front of them sees their left
on the right, the radiological convention.

Layout. One mesh, one primitive (POSITION, NORMAL, indices), one PBR material
(bone, single-sided since faces wind outward), two nodes: the root carries
``FRAME`` and the provenance, its child carries the mesh (and, when compressed,
the dequantisation). Chunks and bufferViews start on 4-byte boundaries.

``compress=True`` writes EXT_meshopt_compression over KHR_mesh_quantization:
positions as uint16 on a uniform grid (error at most half a step, 0.0019 mm for
a 250 mm object), normals octahedral-encoded in 8 bits, triangles and vertices
reordered for locality first. The uncompressed views point to a placeholder
buffer marked ``fallback`` with no data, so both extensions are required.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import meshoptimizer
import numpy as np

from miss.export.vrml import BONE_RGB, DEFAULT_TITLE
from miss.geometry import locality_order, mesh_normals
from miss.scene import Part, Scene, linear_rgb
from miss.types import Mesh, column_bounds

# Rows: glTF X, Y, Z in LPS coordinates (see the module docstring).
LPS_TO_GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
FRAME = np.diag([0.001, 0.001, 0.001, 1.0]) @ np.block(
    [[LPS_TO_GLTF, np.zeros((3, 1))], [np.zeros((1, 3)), np.ones((1, 1))]]
)

# GLB container, little-endian by definition: 12-byte header, then chunks.
_GLB_HEADER = np.dtype([("magic", "S4"), ("version", "<u4"), ("length", "<u4")])
_CHUNK_HEADER = np.dtype([("length", "<u4"), ("type", "<u4")])
_JSON_CHUNK, _BIN_CHUNK = 0x4E4F534A, 0x004E4942  # b"JSON", b"BIN\0" read as uint32

_BYTE, _USHORT, _UINT, _FLOAT = 5120, 5123, 5125, 5126
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_MESHOPT, _QUANTIZATION = "EXT_meshopt_compression", "KHR_mesh_quantization"


@dataclass(frozen=True)
class _Stream:
    """One bufferView's uncompressed content and how its accessor reads it."""

    data: np.ndarray  # (count, ...) C-contiguous, little-endian
    accessor: dict[str, Any]
    target: int
    stride: int | None = None  # bufferView.byteStride, vertex attributes only
    meshopt: dict[str, str] = field(default_factory=dict)  # mode and filter


def write(
    mesh: Mesh,
    *,
    title: str | None = None,
    metadata: dict[str, str] | None = None,
    compress: bool = False,
    ordered: bool = False,
) -> bytes:
    """Encode ``mesh`` as binary glTF 2.0.

    Parameters
    ----------
    mesh : Mesh
        Vertices (N, 3) float32 in LPS mm, faces (F, 3) counter-clockwise from
        outside; normals (N, 3) are computed when ``mesh.normals`` is None.
    title, metadata
        The scene name; metadata goes to ``asset.extras`` and to the root
        node's ``extras.provenance`` (three.js ``userData``).
    compress : bool
        EXT_meshopt_compression with quantised positions and normals (about a
        tenth of the size; needs a loader with the meshopt decoder).
    ordered : bool
        The mesh is already in :func:`miss.geometry.locality_order` (a job's scene is):
        compressed as it is rather than reordered first.

    Returns
    -------
    bytes
        A GLB file.
    """
    normals = mesh_normals(mesh)
    if compress:
        streams, mesh_matrix = _quantized_streams(mesh.vertices, normals, mesh.faces, ordered)
        binary, buffers = _compressed_buffers(streams)
    else:
        streams, mesh_matrix = _float_streams(mesh.vertices, normals, mesh.faces), None
        binary, buffers = _plain_buffers(streams)
    document = {**_scene(streams, title, metadata, mesh_matrix), **buffers}
    if compress:
        document["extensionsUsed"] = document["extensionsRequired"] = [_MESHOPT, _QUANTIZATION]
    return _glb(document, binary)


def _float_streams(vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray) -> list[_Stream]:
    """POSITION and NORMAL as float32 mm exactly as given, indices as uint16 or uint32."""
    positions = np.ascontiguousarray(vertices, dtype="<f4")
    return [
        _Stream(positions, _vec3(_FLOAT, positions), _ARRAY_BUFFER),
        _Stream(np.ascontiguousarray(normals, dtype="<f4"), _vec3(_FLOAT), _ARRAY_BUFFER),
        _index_stream(faces, len(vertices)),
    ]


def _quantized_streams(
    vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray, ordered: bool = False
) -> tuple[list[_Stream], np.ndarray]:
    """Reordered, quantised streams and the mesh-node matrix that restores millimetres.

    Positions become ``q = round((v - lo) / step)`` as uint16 padded to 8 bytes (the
    meshopt attribute codec wants strides divisible by 4; the constant pad costs
    almost nothing compressed). The matrix maps q back: ``v = lo + step * q``.
    """
    if not ordered:  # both codecs predict from the recent past: locality is most of the gain
        mesh = locality_order(Mesh(np.asarray(vertices, np.float32), faces, normals))
        assert mesh.normals is not None  # carried along
        vertices, normals, faces = mesh.vertices, mesh.normals, mesh.faces
    lo, hi = (b.astype(np.float64) for b in column_bounds(vertices))
    extent = float((hi - lo).max())
    step = extent / 65535 if extent > 0 else 1.0  # one step for all axes: a uniform scale
    quantized = np.zeros((len(vertices), 4), dtype="<u2")
    quantized[:, :3] = np.clip(np.rint((vertices - lo) / step), 0, 65535)
    position = _vec3(_USHORT, quantized[:, :3])
    normal = {**_vec3(_BYTE), "normalized": True}
    streams = [
        _Stream(quantized, position, _ARRAY_BUFFER, 8, {"mode": "ATTRIBUTES"}),
        _Stream(
            octahedral(normals),
            normal,
            _ARRAY_BUFFER,
            4,
            {"mode": "ATTRIBUTES", "filter": "OCTAHEDRAL"},
        ),
        _index_stream(faces, len(vertices)),
    ]
    matrix = np.diag([step, step, step, 1.0])
    matrix[:3, 3] = lo
    return streams, matrix


def octahedral(normals: np.ndarray) -> np.ndarray:
    """Unit vectors (N, 3) to meshopt's 8-bit octahedral filter input (N, 4) int8.

    Project onto the octahedron |x| + |y| + |z| = 1, fold the lower half over
    the upper, store x and y as snorm8 and 127 (1.0 at K = 8 bits) in the third
    byte, which the decoder reads to find K; the fourth byte is unused (0).
    """
    n = np.asarray(normals, dtype=np.float64)
    l1 = np.abs(n).sum(axis=1, keepdims=True)
    n = np.divide(n, l1, out=np.zeros_like(n), where=l1 > 0)
    x, y, z = n.T
    sign_x, sign_y = np.where(x >= 0, 1.0, -1.0), np.where(y >= 0, 1.0, -1.0)
    folded_x = np.where(z >= 0, x, (1 - np.abs(y)) * sign_x)
    folded_y = np.where(z >= 0, y, (1 - np.abs(x)) * sign_y)
    out = np.zeros((len(n), 4), dtype=np.int8)
    out[:, 0] = np.rint(folded_x * 127)
    out[:, 1] = np.rint(folded_y * 127)
    out[:, 2] = 127
    return out


def _index_stream(faces: np.ndarray, n_vertices: int) -> _Stream:
    """Triangle indices, uint16 when they fit: 65535 is reserved (primitive restart)."""
    dtype = "<u2" if n_vertices < 65536 else "<u4"
    data = np.ascontiguousarray(faces, dtype=dtype).ravel()
    accessor = {"componentType": _USHORT if dtype == "<u2" else _UINT, "type": "SCALAR"}
    return _Stream(data, accessor, _ELEMENT_ARRAY_BUFFER, meshopt={"mode": "TRIANGLES"})


def _vec3(component_type: int, values: np.ndarray | None = None) -> dict[str, Any]:
    """A VEC3 accessor; with ``values`` (N, 3) also its min and max (required for POSITION)."""
    accessor: dict[str, Any] = {"componentType": component_type, "type": "VEC3"}
    if values is not None:
        # .tolist() gives Python numbers equal to the stored float32/uint16 values, as glTF asks.
        lo, hi = column_bounds(values)
        accessor["min"], accessor["max"] = lo.tolist(), hi.tolist()
    return accessor


def _layout(sizes: list[int]) -> tuple[list[int], int]:
    """Offsets that start each block on a 4-byte boundary, and the padded total."""
    offsets, end = [], 0
    for size in sizes:
        end += -end % 4
        offsets.append(end)
        end += size
    return offsets, end + -end % 4


def _concatenated(blobs: list[bytes]) -> tuple[bytes, list[int]]:
    """The blobs laid out by ``_layout``, zero-padded; returns (bytes, offsets)."""
    offsets, total = _layout([len(blob) for blob in blobs])
    out = bytearray(total)
    for blob, offset in zip(blobs, offsets, strict=True):
        out[offset : offset + len(blob)] = blob
    return bytes(out), offsets


def _view(buffer: int, offset: int, stream: _Stream) -> dict[str, Any]:
    """The bufferView JSON for ``stream`` stored uncompressed at ``offset`` in ``buffer``."""
    view = {"buffer": buffer, "byteOffset": offset, "byteLength": stream.data.nbytes}
    if stream.stride:
        view["byteStride"] = stream.stride
    view["target"] = stream.target
    return view


def _plain_buffers(streams: list[_Stream]) -> tuple[bytes, dict[str, Any]]:
    """The streams as they are, in buffer 0 (the GLB BIN chunk)."""
    binary, offsets = _concatenated([s.data.tobytes() for s in streams])
    views = [_view(0, offset, s) for s, offset in zip(streams, offsets, strict=True)]
    return binary, {"buffers": [{"byteLength": len(binary)}], "bufferViews": views}


def _compressed_buffers(streams: list[_Stream]) -> tuple[bytes, dict[str, Any]]:
    """Meshopt-encoded streams in buffer 0; the decoded views' ranges in buffer 1.

    Buffer 1 is the extension's placeholder: no data, only a byteLength large
    enough for the decoded views, flagged ``fallback``; index 1 so it cannot be
    mistaken for the GLB BIN chunk, which is always buffer 0.
    """
    encoded = [_meshopt_encode(s) for s in streams]
    binary, offsets = _concatenated(encoded)
    raw_offsets, raw_total = _layout([s.data.nbytes for s in streams])
    views = []
    for s, blob, offset, raw_offset in zip(streams, encoded, offsets, raw_offsets, strict=True):
        view = _view(1, raw_offset, s)
        view["extensions"] = {
            _MESHOPT: {
                "buffer": 0,
                "byteOffset": offset,
                "byteLength": len(blob),
                "byteStride": s.data.nbytes // len(s.data),
                "count": len(s.data),
                **s.meshopt,
            }
        }
        views.append(view)
    buffers = [
        {"byteLength": len(binary)},
        {"byteLength": raw_total, "extensions": {_MESHOPT: {"fallback": True}}},
    ]
    return binary, {"buffers": buffers, "bufferViews": views}


def _meshopt_encode(stream: _Stream) -> bytes:
    """One bufferView through the meshopt codec its ``mode`` names."""
    count = len(stream.data)
    if stream.meshopt["mode"] == "TRIANGLES":
        # The extension specifies index codec version 1 (header byte 0xe1).
        meshoptimizer.encode_index_version(1)
        return meshoptimizer.encode_index_buffer(stream.data.astype(np.uint32), count)
    # The extension specifies vertex codec version 0 (header byte 0xa0); newer
    # meshoptimizer releases may default to version 1, which its decoders reject.
    meshoptimizer.encode_vertex_version(0)
    return meshoptimizer.encode_vertex_buffer(stream.data, count, stream.data.nbytes // count)


def _scene(
    streams: list[_Stream],
    title: str | None,
    metadata: dict[str, str] | None,
    mesh_matrix: np.ndarray | None,
) -> dict[str, Any]:
    """Everything in the JSON except buffers: accessors, mesh, material, nodes, asset."""
    accessors = [
        {"bufferView": i, **s.accessor, "count": len(s.data)} for i, s in enumerate(streams)
    ]
    primitive = {"attributes": {"POSITION": 0, "NORMAL": 1}, "indices": 2, "material": 0, "mode": 4}
    root: dict[str, Any] = {
        "name": "patient LPS mm to glTF m",
        "matrix": _column_major(FRAME),
        "children": [1],
    }
    # Node extras become three.js userData: the viewer finds provenance on the model itself.
    root["extras"] = {"frame": "glTF +X = patient left, +Y = superior, +Z = anterior; data in mm"}
    if metadata:
        root["extras"]["provenance"] = {str(key): str(value) for key, value in metadata.items()}
    surface: dict[str, Any] = {"name": "surface", "mesh": 0}
    if mesh_matrix is not None:
        surface["matrix"] = _column_major(mesh_matrix)
    asset: dict[str, Any] = {"version": "2.0", "generator": "MISS (Medical Image Sharing System)"}
    if metadata:
        asset["extras"] = {str(key): str(value) for key, value in metadata.items()}
    return {
        "asset": asset,
        "scene": 0,
        "scenes": [{"name": title or DEFAULT_TITLE, "nodes": [0]}],
        "nodes": [root, surface],
        "meshes": [{"name": "surface", "primitives": [primitive]}],
        "materials": [_bone_material()],
        "accessors": accessors,
    }


def _bone_material() -> dict[str, Any]:
    """PBR bone: sRGB ``BONE_RGB`` made linear (glTF factors are linear), matte, one-sided."""
    srgb = np.array(BONE_RGB)
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return {
        "name": "bone",
        "pbrMetallicRoughness": {
            "baseColorFactor": [*np.round(linear, 4).tolist(), 1.0],
            "metallicFactor": 0.0,
            "roughnessFactor": 0.6,
        },
        "doubleSided": False,
    }


def _column_major(matrix: np.ndarray) -> list[float]:
    """A 4x4 matrix as glTF's 16 numbers, column by column."""
    return [float(x) for x in np.asarray(matrix).T.ravel()]


def _glb(document: dict[str, Any], binary: bytes) -> bytes:
    """The GLB container: header, JSON chunk padded with spaces, BIN chunk padded with zeros."""
    text = json.dumps(document, separators=(",", ":")).encode("utf-8")
    text += b" " * (-len(text) % 4)
    binary += b"\0" * (-len(binary) % 4)
    total = _GLB_HEADER.itemsize + 2 * _CHUNK_HEADER.itemsize + len(text) + len(binary)
    header = np.array((b"glTF", 2, total), dtype=_GLB_HEADER).tobytes()
    json_chunk = np.array((len(text), _JSON_CHUNK), dtype=_CHUNK_HEADER).tobytes()
    bin_chunk = np.array((len(binary), _BIN_CHUNK), dtype=_CHUNK_HEADER).tobytes()
    return header + json_chunk + text + bin_chunk + binary


# ------------------------------------------------------------------ scenes


def write_scene(
    scene: Scene,
    *,
    title: str | None = None,
    metadata: dict[str, str] | None = None,
    compress: bool = False,
    ordered: bool = False,
) -> bytes:
    """Encode a :class:`~miss.scene.Scene` as binary glTF 2.0: one mesh and material per part.

    Node, mesh and material carry the part's name. The material's base colour
    is the part's colour made linear with its opacity as alpha; a translucent
    part (opacity < 1) uses ``alphaMode: BLEND``. Each part node's ``extras``
    (three.js ``userData``) hold ``label``, ``volume_ml`` and ``area_cm2``. The
    root node carries ``FRAME`` as for a single mesh; ``compress`` and ``ordered`` as
    :func:`write`.
    """
    streams: list[_Stream] = []
    matrices: list[np.ndarray | None] = []
    for part in scene.parts:
        mesh = part.mesh
        normals = mesh_normals(mesh)
        if compress:
            part_streams, matrix = _quantized_streams(mesh.vertices, normals, mesh.faces, ordered)
        else:
            part_streams, matrix = _float_streams(mesh.vertices, normals, mesh.faces), None
        streams += part_streams
        matrices.append(matrix)
    binary, buffers = _compressed_buffers(streams) if compress else _plain_buffers(streams)
    document = {**_parts_document(scene, streams, matrices, title, metadata), **buffers}
    if compress:
        document["extensionsUsed"] = document["extensionsRequired"] = [_MESHOPT, _QUANTIZATION]
    return _glb(document, binary)


def _parts_document(
    scene: Scene,
    streams: list[_Stream],
    matrices: list[np.ndarray | None],
    title: str | None,
    metadata: dict[str, str] | None,
) -> dict[str, Any]:
    """The JSON without buffers: three accessors, a mesh, a material and a node per part."""
    accessors = [
        {"bufferView": i, **s.accessor, "count": len(s.data)} for i, s in enumerate(streams)
    ]
    n = len(scene.parts)
    root: dict[str, Any] = {
        "name": "patient LPS mm to glTF m",
        "matrix": _column_major(FRAME),
        "children": list(range(1, n + 1)),
        "extras": {"frame": "glTF +X = patient left, +Y = superior, +Z = anterior; data in mm"},
    }
    asset: dict[str, Any] = {"version": "2.0", "generator": "MISS (Medical Image Sharing System)"}
    if metadata:
        root["extras"]["provenance"] = {str(k): str(v) for k, v in metadata.items()}
        asset["extras"] = {str(k): str(v) for k, v in metadata.items()}
    meshes, nodes = [], [root]
    for i, (part, matrix) in enumerate(zip(scene.parts, matrices, strict=True)):
        primitive = {
            "attributes": {"POSITION": 3 * i, "NORMAL": 3 * i + 1},
            "indices": 3 * i + 2,
            "material": i,
            "mode": 4,
        }
        meshes.append({"name": part.name, "primitives": [primitive]})
        nodes.append(_part_node(part, i, matrix))
    return {
        "asset": asset,
        "scene": 0,
        "scenes": [{"name": title or scene.title, "nodes": [0]}],
        "nodes": nodes,
        "meshes": meshes,
        "materials": [_part_material(part) for part in scene.parts],
        "accessors": accessors,
    }


def _part_node(part: Part, index: int, matrix: np.ndarray | None) -> dict[str, Any]:
    """A part's node: name, mesh, measures in ``extras``, dequantisation when compressed."""
    node: dict[str, Any] = {"name": part.name, "mesh": index}
    if matrix is not None:
        node["matrix"] = _column_major(matrix)
    node["extras"] = {
        "label": part.label,
        "volume_ml": round(part.volume_ml, 4),
        "area_cm2": round(part.area_cm2, 4),
        "opacity": part.opacity,
    }
    return node


def _part_material(part: Part) -> dict[str, Any]:
    """PBR material in the part's colour (linear factors), blended when translucent."""
    material: dict[str, Any] = {
        "name": part.name,
        "pbrMetallicRoughness": {
            "baseColorFactor": [*linear_rgb(part.color), round(part.opacity, 4)],
            "metallicFactor": 0.0,
            "roughnessFactor": 0.6,
        },
        "doubleSided": False,
    }
    if part.opacity < 1.0:
        material["alphaMode"] = "BLEND"
    return material
