"""Round trips for every writer through a reader that is not ours.

trimesh reads GLB, STL, PLY and OBJ; lxml and xml.etree read X3D; VRML is read by
a strict little parser below (header, balanced brackets, counts, -1 terminators,
index range). The compressed GLB is decoded with meshoptimizer's own decoders.
"""

from __future__ import annotations

import gzip
import io
import json
import re
import struct
import xml.etree.ElementTree as ET

import meshoptimizer
import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from lxml import etree

from miss.errors import BadParameter, EmptySurface, UnsupportedFormat
from miss.export import FORMATS, WRITERS, export, mime_type
from miss.export._text import format_rows
from miss.export.gltf import FRAME
from miss.geometry import vertex_normals
from miss.types import Mesh

METADATA = {"level": "95.5 HU", "software": "MISS 0.1.0", "note": 'quote " and back\\slash'}
TITLE = 'Sphere "r80" <test> & more'

COORD_TOL = 0.0005 + 1e-6  # 3 decimals of a mm
NORMAL_TOL = 0.00005 + 1e-6  # 4 decimals


def _mesh_from(tm: trimesh.Trimesh, with_normals: bool = False) -> Mesh:
    normals = np.asarray(tm.vertex_normals, dtype=np.float32) if with_normals else None
    return Mesh(tm.vertices.astype(np.float32), tm.faces.astype(np.int32), normals)


@pytest.fixture(scope="module")
def sphere() -> Mesh:
    """Icosphere of radius 80 mm centred at the origin, 1280 triangles."""
    return _mesh_from(trimesh.creation.icosphere(subdivisions=3, radius=80.0))


@pytest.fixture(scope="module")
def skewed() -> Mesh:
    """The sphere under an odd affine (shear, anisotropic scale, det > 0) far in negative space."""
    tm = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    affine = np.array(
        [
            [97.3, 12.5, 0.0, -512.25],
            [0.0, 41.7, -8.1, -0.0004],
            [3.3, 0.0, 133.9, -1777.777],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    assert np.linalg.det(affine[:3, :3]) > 0  # keeps the winding outward
    tm.apply_transform(affine)
    return _mesh_from(tm, with_normals=True)


def _normals(mesh: Mesh) -> np.ndarray:
    """The normals a writer must use: the mesh's own, else MISS's area-weighted ones."""
    return mesh.normals if mesh.normals is not None else vertex_normals(mesh.vertices, mesh.faces)


def _canonical(faces: np.ndarray) -> np.ndarray:
    """Faces rolled so the smallest index leads (winding kept), rows sorted: order-free comparison."""
    faces = np.asarray(faces)
    rolled = np.array([np.roll(f, -int(np.argmin(f))) for f in faces])
    return rolled[np.lexsort(rolled.T[::-1])]


def _triangles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3, 3) corner coordinates: independent of how a reader numbers vertices."""
    return np.asarray(vertices, dtype=np.float64)[np.asarray(faces)]


# ---------------------------------------------------------------- registry


def test_registry_lists_every_format_with_its_mime_type() -> None:
    assert FORMATS == ["wrl", "wrz", "x3d", "glb", "plain.glb", "stl", "ply", "obj", "3mf"]
    expected = {
        "wrl": "model/vrml",
        "wrz": "model/vrml",
        "x3d": "model/x3d+xml",
        "glb": "model/gltf-binary",
        "plain.glb": "model/gltf-binary",
        "stl": "model/stl",
        "ply": "model/ply",
        "obj": "model/obj",
        "3mf": "model/3mf",
    }
    assert {fmt: mime_type(fmt) for fmt in FORMATS} == expected
    assert WRITERS["wrl"].legacy_mime == "x-world/x-vrml"
    binary = ["wrz", "glb", "plain.glb", "stl", "ply", "3mf"]
    assert [fmt for fmt in FORMATS if WRITERS[fmt].binary] == binary


@pytest.mark.parametrize("spelling", ["wrl", ".wrl", "WRL", ".Wrl", " wrl "])
def test_format_spellings_are_equivalent(sphere: Mesh, spelling: str) -> None:
    assert export(sphere, spelling) == export(sphere, "wrl")
    assert mime_type(spelling) == "model/vrml"


def test_unknown_format_names_the_known_ones(sphere: Mesh) -> None:
    with pytest.raises(UnsupportedFormat) as caught:
        export(sphere, "fbx")
    message = str(caught.value)
    assert "'fbx'" in message
    assert all(fmt in message for fmt in FORMATS)
    with pytest.raises(UnsupportedFormat):
        mime_type("3ds")


def test_unknown_option_is_refused_with_the_options_it_takes(sphere: Mesh) -> None:
    with pytest.raises(BadParameter, match="compress"):
        export(sphere, "stl", compress=True)
    with pytest.raises(BadParameter, match="it takes: compress"):
        export(sphere, "glb", level=9)


def test_empty_mesh_is_an_empty_surface_error() -> None:
    empty = Mesh(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.int32))
    with pytest.raises(EmptySurface, match="no triangles"):
        export(empty, "glb")


def test_out_of_range_face_index_is_refused(sphere: Mesh) -> None:
    broken = Mesh(sphere.vertices, sphere.faces.copy())
    broken.faces[0, 0] = sphere.n_vertices
    with pytest.raises(ValueError, match="outside"):
        export(broken, "obj")


@pytest.mark.parametrize("fmt", ["wrl", "wrz", "x3d", "glb", "stl", "ply", "obj", "3mf"])
def test_every_writer_is_deterministic(sphere: Mesh, fmt: str) -> None:
    assert export(sphere, fmt, title=TITLE, metadata=METADATA) == export(
        sphere, fmt, title=TITLE, metadata=METADATA
    )


# ---------------------------------------------------------------- VRML


_TOKEN = re.compile(r'"(?:[^"\\]|\\.)*"|[{}\[\]]|[^\s,{}\[\]"#]+')


def _tokenise(text: str) -> list[str]:
    """VRML97 tokens: strings, brackets, words; commas are whitespace, # starts a comment."""
    tokens: list[str] = []
    for line in text.splitlines():
        pos = 0
        while pos < len(line):
            if line[pos] == "#":
                break  # a comment runs to the end of the line (strings are matched first)
            match = _TOKEN.match(line, pos)
            if match is None:
                pos += 1
                continue
            tokens.append(match.group())
            pos = match.end()
    return tokens


def _is_field_name(token: str) -> bool:
    return bool(re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", token)) and token not in ("TRUE", "FALSE")


def _parse_node(tokens: list[str], i: int) -> tuple[dict, int]:
    """``Type { field value ... }`` -> ({"#type": Type, field: value}, next index)."""
    node: dict = {"#type": tokens[i]}  # "#" cannot start a field name, so no clash
    assert tokens[i + 1] == "{", f"expected '{{' after {tokens[i]}"
    i += 2
    while tokens[i] != "}":
        name = tokens[i]
        assert _is_field_name(name), f"bad field name {name!r}"
        node[name], i = _parse_value(tokens, i + 1)
    return node, i + 1


def _parse_value(tokens: list[str], i: int) -> tuple[object, int]:
    if tokens[i] == "[":
        items, i = [], i + 1
        while tokens[i] != "]":
            if _is_field_name(tokens[i]) and tokens[i + 1] == "{":
                item, i = _parse_node(tokens, i)
            else:
                item, i = tokens[i], i + 1
            items.append(item)
        return items, i + 1
    if _is_field_name(tokens[i]) and tokens[i + 1] == "{":
        return _parse_node(tokens, i)
    values = []
    while tokens[i] != "}" and not _is_field_name(tokens[i]):
        values.append(tokens[i])
        i += 1
    return values, i


def _parse_vrml(data: bytes) -> list[dict]:
    text = data.decode("utf-8")
    assert text.startswith("#VRML V2.0 utf8\n")
    tokens = _tokenise(text)
    assert tokens.count("{") == tokens.count("}") and tokens.count("[") == tokens.count("]")
    nodes, i = [], 0
    while i < len(tokens):
        node, i = _parse_node(tokens, i)
        nodes.append(node)
    return nodes


def _sf_string(token: str) -> str:
    assert token.startswith('"') and token.endswith('"')
    return re.sub(r"\\(.)", r"\1", token[1:-1])


@pytest.mark.parametrize("fmt", FORMATS)
def test_a_title_from_an_undecodable_file_name_is_written(sphere: Mesh, fmt: str) -> None:
    """``miss convert`` titles a model with its file's name; a non-UTF-8 byte in it reaches
    the writers as a lone surrogate, which UTF-8 cannot encode: U+FFFD instead of an error."""
    title = b"sch\xe4del.nii".decode("utf-8", "surrogateescape")
    data = export(sphere, fmt, title=title, metadata={"source\udcff": "x"})
    if fmt in ("wrl", "x3d", "obj"):
        text = data.decode("utf-8")  # valid UTF-8 throughout
        assert "sch\ufffddel" in text
    if fmt == "wrz":
        assert "sch\ufffddel" in gzip.decompress(data).decode("utf-8")


@pytest.mark.parametrize("name", ["sphere", "skewed"])
def test_vrml_parses_strictly_and_matches_the_mesh(
    name: str, request: pytest.FixtureRequest
) -> None:
    mesh: Mesh = request.getfixturevalue(name)
    nodes = _parse_vrml(export(mesh, "wrl", title=TITLE, metadata=METADATA))
    by_type = {node["#type"]: node for node in nodes}
    assert set(by_type) == {"WorldInfo", "NavigationInfo", "Viewpoint", "Shape"}
    info = by_type["WorldInfo"]
    assert _sf_string(info["title"][0]) == TITLE
    assert [_sf_string(s) for s in info["info"]] == [f"{k}: {v}" for k, v in METADATA.items()]

    faceset = by_type["Shape"]["geometry"]
    assert faceset["#type"] == "IndexedFaceSet"
    assert (
        faceset["solid"] == ["TRUE"]
        and faceset["ccw"] == ["TRUE"]
        and faceset["normalPerVertex"] == ["TRUE"]
    )
    points = np.array(faceset["coord"]["point"], dtype=np.float64).reshape(-1, 3)
    vectors = np.array(faceset["normal"]["vector"], dtype=np.float64).reshape(-1, 3)
    index = np.array(faceset["coordIndex"], dtype=np.int64).reshape(-1, 4)
    assert len(points) == len(vectors) == mesh.n_vertices
    assert len(index) == mesh.n_triangles
    assert (index[:, 3] == -1).all()
    assert index[:, :3].min() >= 0 and index[:, :3].max() < mesh.n_vertices
    np.testing.assert_array_equal(index[:, :3], mesh.faces)
    np.testing.assert_allclose(points, mesh.vertices, rtol=0, atol=COORD_TOL)
    np.testing.assert_allclose(vectors, _normals(mesh), rtol=0, atol=NORMAL_TOL)


def test_vrml_computes_unit_normals_when_the_mesh_has_none(sphere: Mesh) -> None:
    faceset = _parse_vrml(export(sphere, "wrl"))[-1]["geometry"]
    vectors = np.array(faceset["normal"]["vector"], dtype=np.float64).reshape(-1, 3)
    points = np.array(faceset["coord"]["point"], dtype=np.float64).reshape(-1, 3)
    # On a sphere centred at the origin the outward normal is the position direction.
    radial = points / np.linalg.norm(points, axis=1, keepdims=True)
    assert np.einsum("ij,ij->i", vectors, radial).min() > 0.99


def test_wrz_gunzips_to_the_wrl_bytes(skewed: Mesh) -> None:
    wrz = export(skewed, "wrz", title=TITLE, metadata=METADATA)
    assert wrz[:2] == b"\x1f\x8b"
    assert struct.unpack("<I", wrz[4:8])[0] == 0  # mtime 0: reproducible bytes
    assert gzip.decompress(wrz) == export(skewed, "wrl", title=TITLE, metadata=METADATA)


# ---------------------------------------------------------------- X3D


def test_x3d_reads_back_with_lxml_and_etree(skewed: Mesh) -> None:
    data = export(skewed, "x3d", title=TITLE, metadata=METADATA)
    root = etree.fromstring(data)  # lxml: strict XML, no recovery
    assert root.tag == "X3D" and root.get("version") == "3.3"
    metas = {m.get("name"): m.get("content") for m in root.iter("meta")}
    assert metas["title"] == TITLE
    assert all(metas[key] == value for key, value in METADATA.items())

    shape = ET.fromstring(data).find("Scene/Shape")
    triangles = shape.find("IndexedTriangleSet")
    index = np.array(triangles.get("index").split(), dtype=np.int64).reshape(-1, 3)
    points = np.array(triangles.find("Coordinate").get("point").split(), dtype=np.float64).reshape(
        -1, 3
    )
    vectors = np.array(triangles.find("Normal").get("vector").split(), dtype=np.float64).reshape(
        -1, 3
    )
    assert triangles.get("solid") == "true" and triangles.get("ccw") == "true"
    np.testing.assert_array_equal(index, skewed.faces)
    np.testing.assert_allclose(points, skewed.vertices, rtol=0, atol=COORD_TOL)
    np.testing.assert_allclose(vectors, skewed.normals, rtol=0, atol=NORMAL_TOL)
    assert shape.find("Appearance/Material").get("diffuseColor")


# ---------------------------------------------------------------- glTF


def _parse_glb(data: bytes) -> tuple[dict, bytes]:
    """GLB container by hand: header, JSON chunk, BIN chunk, with the alignment rules."""
    magic, version, length = struct.unpack_from("<4sII", data, 0)
    assert (magic, version, length) == (b"glTF", 2, len(data))
    json_length, json_type = struct.unpack_from("<II", data, 12)
    assert json_type == 0x4E4F534A and json_length % 4 == 0
    document = json.loads(data[20 : 20 + json_length])
    bin_length, bin_type = struct.unpack_from("<II", data, 20 + json_length)
    assert bin_type == 0x004E4942 and bin_length % 4 == 0
    start = 28 + json_length
    assert start + bin_length == len(data)
    return document, data[start : start + bin_length]


_COMPONENT = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_WIDTH = {"SCALAR": 1, "VEC3": 3}


def _read_accessor(document: dict, views: list[bytes], index: int) -> np.ndarray:
    """Accessor ``index`` from decoded bufferView bytes, honouring byteStride."""
    accessor = document["accessors"][index]
    view = document["bufferViews"][accessor["bufferView"]]
    dtype = np.dtype(_COMPONENT[accessor["componentType"]])
    width = _WIDTH[accessor["type"]]
    stride = view.get("byteStride", dtype.itemsize * width)
    raw = np.frombuffer(views[accessor["bufferView"]], dtype=np.uint8)
    rows = raw[: accessor["count"] * stride].reshape(accessor["count"], stride)
    return rows[:, : dtype.itemsize * width].copy().view(dtype).reshape(accessor["count"], width)


def _plain_views(document: dict, binary: bytes) -> list[bytes]:
    views = []
    for view in document["bufferViews"]:
        assert view["buffer"] == 0 and view["byteOffset"] % 4 == 0
        views.append(binary[view["byteOffset"] : view["byteOffset"] + view["byteLength"]])
    return views


def test_glb_root_frame_is_a_proper_rotation_to_y_up_metres() -> None:
    rotation = FRAME[:3, :3] / 0.001
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(rotation) == pytest.approx(1.0)
    left, posterior, superior = np.eye(3)
    np.testing.assert_allclose(rotation @ left, [1, 0, 0])  # +X = left
    np.testing.assert_allclose(rotation @ superior, [0, 1, 0])  # +Y = up
    np.testing.assert_allclose(rotation @ -posterior, [0, 0, 1])  # +Z = anterior, glTF's front


@pytest.mark.parametrize("name", ["sphere", "skewed"])
def test_glb_accessors_hold_the_mesh_in_mm_and_the_root_holds_the_frame(
    name: str, request: pytest.FixtureRequest
) -> None:
    mesh: Mesh = request.getfixturevalue(name)
    document, binary = _parse_glb(export(mesh, "glb", title=TITLE, metadata=METADATA))
    views = _plain_views(document, binary)
    primitive = document["meshes"][0]["primitives"][0]
    positions = _read_accessor(document, views, primitive["attributes"]["POSITION"])
    normals = _read_accessor(document, views, primitive["attributes"]["NORMAL"])
    indices = _read_accessor(document, views, primitive["indices"])
    np.testing.assert_array_equal(positions, mesh.vertices)
    np.testing.assert_array_equal(indices.reshape(-1, 3), mesh.faces)
    if mesh.normals is not None:
        np.testing.assert_array_equal(normals, mesh.normals)
    accessor = document["accessors"][primitive["attributes"]["POSITION"]]
    assert accessor["min"] == mesh.vertices.min(axis=0).tolist()
    assert accessor["max"] == mesh.vertices.max(axis=0).tolist()
    assert document["accessors"][primitive["indices"]]["componentType"] == 5123  # uint16

    root = document["nodes"][document["scenes"][0]["nodes"][0]]
    np.testing.assert_allclose(np.array(root["matrix"]).reshape(4, 4).T, FRAME)
    child = document["nodes"][root["children"][0]]
    assert child["mesh"] == 0 and "matrix" not in child
    assert document["scenes"][0]["name"] == TITLE
    assert document["asset"]["version"] == "2.0" and document["asset"]["extras"] == METADATA
    assert root["extras"]["provenance"] == METADATA
    material = document["materials"][primitive["material"]]
    assert (
        material["doubleSided"] is False and material["pbrMetallicRoughness"]["metallicFactor"] == 0
    )


def test_glb_loads_in_trimesh_at_metre_scale_y_up(skewed: Mesh) -> None:
    scene = trimesh.load(io.BytesIO(export(skewed, "glb")), file_type="glb", process=False)
    loaded = scene.to_mesh()
    assert len(loaded.faces) == skewed.n_triangles
    expected = (FRAME[:3, :3] @ skewed.vertices.astype(np.float64).T).T
    np.testing.assert_allclose(
        _triangles(loaded.vertices, loaded.faces), _triangles(expected, skewed.faces), atol=1e-9
    )
    assert loaded.is_winding_consistent and loaded.volume > 0  # outward winding survived


def test_glb_switches_to_uint32_indices_above_65535_vertices() -> None:
    n = 70_000
    vertices = np.column_stack([np.arange(n), np.arange(n) % 7, np.arange(n) % 11]).astype(
        np.float32
    )
    faces = np.column_stack([np.arange(n - 2), np.arange(1, n - 1), np.arange(2, n)]).astype(
        np.int32
    )
    document, binary = _parse_glb(export(Mesh(vertices, faces), "glb"))
    primitive = document["meshes"][0]["primitives"][0]
    assert document["accessors"][primitive["indices"]]["componentType"] == 5125
    indices = _read_accessor(document, _plain_views(document, binary), primitive["indices"])
    np.testing.assert_array_equal(indices.reshape(-1, 3), faces)


def _decode_meshopt_views(document: dict, binary: bytes) -> list[bytes]:
    """Each bufferView decoded from its EXT_meshopt_compression range in buffer 0."""
    views = []
    for view in document["bufferViews"]:
        ext = view["extensions"]["EXT_meshopt_compression"]
        assert ext["buffer"] == 0 and ext["byteOffset"] % 4 == 0
        assert view["byteLength"] == ext["byteStride"] * ext["count"]
        blob = binary[ext["byteOffset"] : ext["byteOffset"] + ext["byteLength"]]
        if ext["mode"] == "TRIANGLES":
            assert blob[0] == 0xE1  # index codec version 1, as the extension specifies
            # Decode to 4-byte indices (the bitstream does not depend on the width;
            # the Python wrapper returns a uint32 array whatever width is asked for).
            decoded = meshoptimizer.decode_index_buffer(ext["count"], 4, blob)
            views.append(decoded.astype(f"<u{ext['byteStride']}").tobytes())
            continue
        assert blob[0] == 0xA0  # vertex codec version 0, as the extension specifies
        raw = meshoptimizer.decode_vertex_buffer(ext["count"], ext["byteStride"], blob)
        raw = raw.view(np.uint8).reshape(ext["count"], ext["byteStride"])
        if ext.get("filter") == "OCTAHEDRAL":
            raw = meshoptimizer.decode_filter_oct(
                raw.view(np.int8).copy(), ext["count"], ext["byteStride"]
            )
        views.append(raw.tobytes())
    return views


def test_compressed_glb_decodes_to_the_same_surface(skewed: Mesh) -> None:
    data = export(skewed, "glb", compress=True, title=TITLE, metadata=METADATA)
    document, binary = _parse_glb(data)
    required = {"EXT_meshopt_compression", "KHR_mesh_quantization"}
    assert set(document["extensionsRequired"]) == set(document["extensionsUsed"]) == required
    fallback = document["buffers"][1]
    assert "uri" not in fallback and fallback["extensions"]["EXT_meshopt_compression"] == {
        "fallback": True
    }
    assert all(v["buffer"] == 1 and v["byteOffset"] % 4 == 0 for v in document["bufferViews"])
    assert (
        max(v["byteOffset"] + v["byteLength"] for v in document["bufferViews"])
        <= fallback["byteLength"]
    )
    assert document["buffers"][0]["byteLength"] == len(binary)

    views = _decode_meshopt_views(document, binary)
    primitive = document["meshes"][0]["primitives"][0]
    quantized = _read_accessor(document, views, primitive["attributes"]["POSITION"]).astype(
        np.float64
    )
    normals = _read_accessor(document, views, primitive["attributes"]["NORMAL"]) / 127.0
    faces = _read_accessor(document, views, primitive["indices"]).reshape(-1, 3)
    accessor = document["accessors"][primitive["attributes"]["POSITION"]]
    assert (
        accessor["min"] == quantized.min(axis=0).tolist()
        and accessor["max"] == quantized.max(axis=0).tolist()
    )

    root = document["nodes"][0]
    np.testing.assert_allclose(np.array(root["matrix"]).reshape(4, 4).T, FRAME)
    dequantize = np.array(document["nodes"][root["children"][0]]["matrix"]).reshape(4, 4).T
    positions = quantized @ dequantize[:3, :3].T + dequantize[:3, 3]
    step = dequantize[0, 0]
    assert step == pytest.approx(np.ptp(skewed.vertices, axis=0).max() / 65535)
    # Triangles and vertices were reordered (and triangles rotated) for compression:
    # match each decoded vertex to the nearest original, then compare index triples.
    distance = np.linalg.norm(positions[:, None, :] - skewed.vertices[None, :, :], axis=2)
    original = distance.argmin(axis=1)
    assert distance.min(axis=1).max() <= np.sqrt(3) * step / 2 + 1e-4
    np.testing.assert_array_equal(_canonical(original[faces]), _canonical(skewed.faces))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cosine = np.einsum("ij,ij->i", normals, skewed.normals[original])
    assert cosine.min() > np.cos(np.radians(1.5))  # 8-bit octahedral: at most 1.18 degrees off


def test_compressed_glb_is_under_8_bytes_per_triangle() -> None:
    sphere = _mesh_from(
        trimesh.creation.icosphere(subdivisions=5, radius=125.0)
    )  # 250 mm, 20480 triangles
    assert len(export(sphere, "glb", compress=True)) / sphere.n_triangles < 8
    assert len(export(sphere, "glb")) / sphere.n_triangles > 16  # the plain file, for scale


# ---------------------------------------------------------------- STL, PLY, OBJ


def _load(data: bytes, fmt: str) -> trimesh.Trimesh:
    # maintain_order only for PLY: trimesh's OBJ path with it warns on unused vertices.
    return trimesh.load(io.BytesIO(data), file_type=fmt, process=False, maintain_order=fmt == "ply")


@pytest.mark.parametrize("name", ["sphere", "skewed"])
def test_stl_reads_back_with_outward_unit_facet_normals(
    name: str, request: pytest.FixtureRequest
) -> None:
    mesh: Mesh = request.getfixturevalue(name)
    data = export(mesh, "stl", title=TITLE)
    assert len(data) == 84 + 50 * mesh.n_triangles and not data.startswith(b"solid")
    loaded = _load(data, "stl")
    assert len(loaded.faces) == mesh.n_triangles
    np.testing.assert_array_equal(
        _triangles(loaded.vertices, loaded.faces), _triangles(mesh.vertices, mesh.faces)
    )
    stored = np.frombuffer(
        data[84:], dtype=np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    )
    recomputed = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False).face_normals
    np.testing.assert_allclose(stored["n"], recomputed, atol=1e-5)


@pytest.mark.parametrize("name", ["sphere", "skewed"])
def test_ply_reads_back_exactly_with_normals_and_comments(
    name: str, request: pytest.FixtureRequest
) -> None:
    mesh: Mesh = request.getfixturevalue(name)
    data = export(mesh, "ply", title=TITLE, metadata=METADATA)
    header = data[: data.index(b"end_header\n")].decode("ascii")
    assert "format binary_little_endian 1.0" in header
    assert f"comment title: {TITLE}" in header and "comment level: 95.5 HU" in header
    loaded = _load(data, "ply")
    np.testing.assert_array_equal(loaded.vertices, mesh.vertices)
    np.testing.assert_array_equal(loaded.faces, mesh.faces)
    if mesh.normals is not None:
        np.testing.assert_array_equal(loaded.vertex_normals, mesh.normals)


@pytest.mark.parametrize("name", ["sphere", "skewed"])
def test_obj_reads_back_within_the_written_precision(
    name: str, request: pytest.FixtureRequest
) -> None:
    mesh: Mesh = request.getfixturevalue(name)
    data = export(mesh, "obj", title=TITLE, metadata=METADATA)
    text = data.decode("utf-8")
    assert "# level: 95.5 HU\n" in text
    assert re.search(r"^f \d+//\d+ \d+//\d+ \d+//\d+$", text, re.MULTILINE)
    loaded = _load(data, "obj")
    assert len(loaded.faces) == mesh.n_triangles
    np.testing.assert_allclose(
        _triangles(loaded.vertices, loaded.faces),
        _triangles(mesh.vertices, mesh.faces),
        rtol=0,
        atol=COORD_TOL,
    )
    if mesh.normals is not None:
        vn = np.array(re.findall(r"^vn (\S+) (\S+) (\S+)$", text, re.MULTILINE), dtype=np.float64)
        np.testing.assert_allclose(vn, mesh.normals, rtol=0, atol=NORMAL_TOL)


# Distinct coordinates: trimesh's OBJ reader warns (NaN texture bounds) when all coincide.
_coordinates = arrays(np.float32, (6, 3), elements=st.floats(-2000, 2000, width=32), unique=True)
_faces = arrays(np.int32, st.tuples(st.integers(1, 8), st.just(3)), elements=st.integers(0, 5))


@settings(max_examples=40, deadline=None)
@given(vertices=_coordinates, faces=_faces)
def test_random_small_meshes_round_trip(vertices: np.ndarray, faces: np.ndarray) -> None:
    mesh = Mesh(vertices, faces)
    expected = _triangles(vertices, faces)
    stl = _load(export(mesh, "stl"), "stl")
    np.testing.assert_array_equal(_triangles(stl.vertices, stl.faces), expected)
    ply = _load(export(mesh, "ply"), "ply")
    np.testing.assert_array_equal(ply.vertices, vertices)
    np.testing.assert_array_equal(ply.faces, faces)
    obj = _load(export(mesh, "obj"), "obj")
    np.testing.assert_allclose(
        _triangles(obj.vertices, obj.faces), expected, rtol=0, atol=COORD_TOL
    )


# ---------------------------------------------------------------- text formatting


def test_format_rows_matches_printf_on_awkward_values() -> None:
    # Not exact decimal ties: printf rounds the binary value, we round value * 1000.
    values = np.array(
        [
            [0.0, -0.0004, 0.0006],
            [999.9996, -999.9996, 1e6 + 0.25],
            [-1.0, 12345.678, -0.5],
            [7.0, -7.0, 0.001],
        ]
    )
    expected = "".join(" ".join(f"{x:.3f}" for x in row) + "\n" for row in values).replace(
        "-0.000", "0.000"
    )
    assert format_rows(values, b"{} {} {}\n", 3).decode() == expected
    ints = np.array([[0, 9, 10], [999, 1000, 123456789], [-5, 0, 42]])
    assert format_rows(ints, b"f {}//{} {}\n") == b"f 0//9 10\nf 999//1000 123456789\nf -5//0 42\n"
    assert format_rows(np.zeros((0, 3)), b"{} {} {}\n", 3) == b""
