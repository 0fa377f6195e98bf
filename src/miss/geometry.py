"""Small vectorised mesh measures shared by surface, decimation, export and tests."""

from __future__ import annotations

import numpy as np

from miss.types import Mesh


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unnormalised face normals, (F, 3) float64; length = 2 x triangle area."""
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return np.cross(b - a, c - a)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals, (N, 3) float32 (zero for unused vertices)."""
    n = len(vertices)
    fn = face_normals(vertices, faces)
    acc = np.zeros((n, 3), dtype=np.float64)
    idx = np.asarray(faces).ravel()
    for axis in range(3):
        acc[:, axis] = np.bincount(idx, weights=np.repeat(fn[:, axis], 3), minlength=n)
    length = np.linalg.norm(acc, axis=1, keepdims=True)
    np.divide(acc, length, out=acc, where=length > 0)
    return acc.astype(np.float32)


def surface_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Total area in mm^2."""
    return float(0.5 * np.linalg.norm(face_normals(vertices, faces), axis=1).sum())


def enclosed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Signed enclosed volume in mm^3 (positive when faces wind outward)."""
    v = np.asarray(vertices, dtype=np.float64)
    a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def compact(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop unreferenced vertices; returns (vertices, faces) renumbered in first-use order."""
    used = np.zeros(len(vertices), dtype=bool)
    used[faces.ravel()] = True
    remap = np.cumsum(used, dtype=np.int64) - 1
    return vertices[used], remap[faces].astype(np.int32)


def locality_order(mesh: Mesh) -> Mesh:
    """``mesh`` with its triangles in vertex-cache order (meshoptimizer's
    ``optimize_vertex_cache``) and its vertices in first-use order, unused ones dropped,
    normals carried along: the same surface, laid out so that neighbours are near in both
    arrays. A mesh with face labels is returned as it is (the optimiser does not say how
    it moved the triangles).

    Every file a job writes holds its scene in this order, so GPUs reuse vertices and
    codecs find small steps (a million triangles' index list encodes to a fifth).
    """
    import meshoptimizer  # lazily: the command line's start does not pay for it

    n = mesh.n_vertices
    if mesh.labels is not None or mesh.n_triangles == 0:
        return mesh
    indices = np.ascontiguousarray(mesh.faces, dtype=np.uint32).ravel()
    optimized = np.zeros_like(indices)
    meshoptimizer.optimize_vertex_cache(optimized, indices, len(indices), n)
    remap = np.zeros(n, dtype=np.uint32)
    used = meshoptimizer.optimize_vertex_fetch_remap(remap, optimized, len(optimized), n)
    keep = remap != np.iinfo(np.uint32).max  # unreferenced vertices map to ~0
    to = remap[keep]

    def moved(values: np.ndarray) -> np.ndarray:
        out = np.zeros((used, *values.shape[1:]), dtype=values.dtype)
        out[to] = values[keep]
        return out

    faces = remap[optimized].reshape(-1, 3).astype(mesh.faces.dtype)
    normals = None if mesh.normals is None else moved(mesh.normals)
    return Mesh(moved(mesh.vertices), faces, normals, None)


def boundary_edge_count(faces: np.ndarray) -> int:
    """Number of edges used by exactly one triangle (0 for a closed surface)."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    key = e[:, 0].astype(np.int64) * (int(faces.max()) + 1) + e[:, 1]
    _, counts = np.unique(key, return_counts=True)
    return int((counts == 1).sum())


def mesh_normals(mesh: Mesh) -> np.ndarray:
    """Unit vertex normals for a file: the mesh's own, or area-weighted ones computed from
    its faces; every one of unit length (:func:`unit_normals`)."""
    normals = vertex_normals(mesh.vertices, mesh.faces) if mesh.normals is None else mesh.normals
    return unit_normals(normals, mesh.vertices, mesh.faces)


def unit_normals(normals: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``normals`` (N, 3) as unit vectors, float32, every one of them (those of unit
    length already are returned unchanged).

    A zero or non-finite normal (a vertex that only degenerate triangles use, gradient
    normals that cancel, a vertex no triangle uses) would be written as a zero vector,
    which glTF forbids (the Khronos validator's ACCESSOR_VECTOR3_NON_UNIT) and which
    lights as black. It becomes, in this order: the area-weighted normal of its
    triangles, the mean of its triangle neighbours' normals, or +z.
    """
    out = np.array(normals, dtype=np.float32)  # unit ones stay as they are, bit for bit
    length = np.sqrt(np.einsum("ij,ij->i", out, out))
    bad = ~(np.isfinite(length) & (length > 1e-12))
    off = ~bad & (np.abs(length - 1) > 1e-5)
    out[off] /= length[off, None]
    out[bad] = 0.0
    faces = np.asarray(faces)
    if bad.any() and len(faces):
        # Only the triangles of the bad vertices matter: both fallbacks sum over them.
        near = faces[bad[faces[:, 0]] | bad[faces[:, 1]] | bad[faces[:, 2]]]
        area_weighted = np.zeros(out.shape)
        normals_of_near = face_normals(vertices, near)
        for k in range(3):
            np.add.at(area_weighted, near[:, k], normals_of_near)
        _fill(out, bad, area_weighted)
        if bad.any():
            neighbours = np.zeros(out.shape)
            for k in range(3):
                for j in range(3):
                    if j != k:
                        np.add.at(neighbours, near[:, k], out[near[:, j]])
            _fill(out, bad, neighbours)
    out[bad] = (0.0, 0.0, 1.0)
    return out


def _fill(out: np.ndarray, bad: np.ndarray, sums: np.ndarray) -> None:
    """Where ``bad`` and ``sums`` has a direction: that direction into ``out``; those
    vertices leave ``bad`` (both changed in place)."""
    length = np.linalg.norm(sums, axis=1)
    found = bad & (length > 1e-12)
    out[found] = sums[found] / length[found, None]
    bad &= ~found
