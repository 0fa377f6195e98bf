"""Label maps to surfaces that share their boundaries (VTK's surface nets).

One pass of ``vtkSurfaceNets3D`` over the whole map gives a single mesh whose
triangles each separate two labels (its ``BoundaryLabels``). Part ``L`` is every
triangle with ``L`` on one side, turned to face out of ``L``; two neighbours
therefore use the very same triangles and vertices on their interface: no gap,
no overlap, not even after smoothing or decimation:

- smoothing moves the shared vertices once (windowed sinc on the whole mesh);
- decimation works on *patches* (the triangles between one pair of labels) with
  their borders locked, so the curves where three labels meet stay where they are
  and every patch still fits its neighbours.

Surface nets' own smoothing is left off: it leaves copies of the same vertex
apart at non-manifold spots (holes) and shrinks thin structures by a fifth.
Unsmoothed, every vertex sits at a voxel-cell centre, so copies weld exactly.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass

import meshoptimizer
import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkFiltersCore import vtkSurfaceNets3D

from miss._vtk import image_data, polydata_to_arrays
from miss.decimate import (
    ERROR_BOUND,
    MAX_ERROR,
    METHOD,
    REDUCE,
    SCHEDULE,
    DecimationReport,
    decimate,
    measured,
)
from miss.errors import BadParameter, EmptySurface
from miss.geometry import compact, vertex_normals
from miss.smooth import windowed_sinc
from miss.spec import PASSBAND
from miss.structures.counts import label_counts
from miss.types import Mesh, Volume

#: Points sampled on each surface when measuring a part's decimation error: a
#: tenth of miss.decimate's default, as a scene measures dozens of parts.
MEASURE_SAMPLES = 10_000


def align_labels(labels: Volume, reference: Volume) -> Volume:
    """Resample a label map onto a reference grid (a CT) by nearest neighbour, in mm.

    Each reference voxel takes the label found at its centre's patient position
    (through both affines); positions outside the label map get 0. A map with
    fewer slices than its CT (same affine otherwise) is simply padded.

    Returns
    -------
    Volume
        data with the reference's dims, the label map's dtype; the reference's affine.
    """
    from scipy import ndimage  # 0.3 s to load: only when a label map is laid over a scan

    to_labels = np.linalg.inv(labels.affine) @ reference.affine  # reference index -> label index
    out = np.zeros(reference.dims, dtype=labels.data.dtype, order="F")
    ndimage.affine_transform(
        labels.data, to_labels[:3, :3], offset=to_labels[:3, 3], output=out,
        order=0, mode="constant", cval=0, prefilter=False,
    )  # fmt: skip
    if labels.data.any() and not out.any():
        raise BadParameter(
            "the label map does not overlap the volume in patient space; check that both "
            "come from the same scan (same frame of reference)."
        )
    notes = [*labels.meta.get("notes", []), "label map resampled onto the volume's grid"]
    return Volume(data=out, affine=reference.affine, meta={**labels.meta, "notes": notes})


def surface_nets(
    data: np.ndarray, labels: Sequence[int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shared multi-label surface of an (X, Y, Z) label array, in index coordinates.

    Returns
    -------
    vertices : (N, 3) float64, voxel indices (welded: one vertex per position)
    faces : (F, 3) int32, wound counter-clockwise seen from ``pairs[:, 1]``'s side
    pairs : (F, 2) int array
        The two labels each triangle separates; ``pairs[:, 0]`` is on its inside.
    """
    padded = np.zeros(tuple(s + 2 for s in data.shape), dtype=data.dtype, order="F")
    padded[1:-1, 1:-1, 1:-1] = data  # background all round: every part closes
    nets = vtkSurfaceNets3D()
    nets.SetInputData(image_data(padded))
    for i, label in enumerate(labels):
        nets.SetLabel(i, float(label))
    nets.SetBackgroundLabel(0)
    nets.SetOutputMeshTypeToTriangles()
    nets.SmoothingOff()
    nets.Update()
    output = nets.GetOutput()
    vertices, faces = polydata_to_arrays(output)
    if len(faces) == 0:
        raise EmptySurface("the label map holds no labels (all voxels are 0); check the file.")
    pairs = numpy_support.vtk_to_numpy(output.GetCellData().GetArray("BoundaryLabels"))
    vertices, faces = _weld(vertices, faces)
    return vertices - 1.0, faces, pairs.astype(np.int64)  # undo the pad


def _weld(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices at the same voxel-cell centre (VTK emits copies at non-manifold cells)."""
    half = np.rint(vertices * 2).astype(np.int64)  # centres sit on half-integers
    half -= half.min(axis=0)
    span = half.max(axis=0) + 1
    key = (half[:, 0] * span[1] + half[:, 1]) * span[2] + half[:, 2]
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    return vertices[first], inverse.reshape(-1)[faces].astype(np.int32)


@dataclass(frozen=True)
class LabelSurface:
    """One label's closed surface before and after decimation, in LPS mm."""

    label: int
    full: Mesh
    mesh: Mesh
    report: DecimationReport


def label_surfaces(
    volume: Volume,
    labels: Sequence[int],
    *,
    smooth: int = 0,
    passband: float = PASSBAND,
    method: str = METHOD,
    reduce: float = REDUCE,
    error_bound: float = ERROR_BOUND,
    max_error: float = MAX_ERROR,
    measure: bool = True,
    schedule: str = SCHEDULE,
) -> list[LabelSurface]:
    """Closed surfaces of ``labels`` that share their boundaries, in patient mm.

    Parameters
    ----------
    volume : Volume
        Integer label map (0 = background).
    labels : sequence of int
        Labels to build parts for; the other labels present still bound them.
    smooth, passband
        Windowed-sinc iterations (0 = none) and passband, see :mod:`miss.smooth`.
    method, reduce, error_bound, max_error, schedule
        As :func:`miss.decimate`. ``"quadric"`` decimates shared patches and keeps
        every interface exact; ``"schroeder"`` decimates each part on its own, so
        neighbours then agree only within the error bound.
    measure : bool
        Measure each part's deviation from its undecimated surface (mm).
    """
    vertices, faces, pairs = shared_surface(volume, labels, smooth, passband)
    full = {label: part_mesh(vertices, faces, pairs, label) for label in labels}
    if method != "quadric":
        out = []
        for label in labels:
            mesh, report = decimate(
                full[label], method, reduce, error_bound,
                max_error=max_error, measure=measure, samples=MEASURE_SAMPLES,
                schedule=schedule,
            )  # fmt: skip
            out.append(LabelSurface(label, full[label], mesh, report))
        return out
    start = time.perf_counter()
    faces, pairs = _decimate_patches(vertices, faces, pairs, full, reduce, max_error)
    share = (time.perf_counter() - start) / max(len(labels), 1)
    return [
        _shared_result(full[label], part_mesh(vertices, faces, pairs, label), label, reduce,
                       error_bound, max_error, share, measure)
        for label in labels
    ]  # fmt: skip


def shared_surface(
    volume: Volume, labels: Sequence[int], smooth: int, passband: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The smoothed shared surface around ``labels``: vertices (N, 3) float32 mm, faces, pairs."""
    present = sorted(label_counts(volume) or {})
    ijk, faces, pairs = surface_nets(volume.data, present)
    wanted = np.isin(pairs, list(labels)).any(axis=1)
    faces, pairs = faces[wanted], pairs[wanted]
    if len(faces) == 0:
        raise EmptySurface(
            f"none of the labels {list(labels)} is in the label map; "
            "list the labels present with 'miss info --json'."
        )
    vertices = ijk @ volume.affine[:3, :3].T + volume.affine[:3, 3]
    if np.linalg.det(volume.affine[:3, :3]) < 0:
        faces = faces[:, ::-1].copy()  # a mirroring affine flips the winding
    return windowed_sinc(vertices, faces, smooth, passband).astype(np.float32), faces, pairs


def part_mesh(vertices: np.ndarray, faces: np.ndarray, pairs: np.ndarray, label: int) -> Mesh:
    """The closed surface of ``label``: its triangles, those seen from outside turned round."""
    inside = faces[pairs[:, 0] == label]
    outside = faces[pairs[:, 1] == label][:, ::-1]
    v, f = compact(vertices, np.concatenate([inside, outside]))
    return Mesh(v, f, vertex_normals(v, f))


def _decimate_patches(
    vertices: np.ndarray,
    faces: np.ndarray,
    pairs: np.ndarray,
    full: dict[int, Mesh],
    reduce: float,
    max_error: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Decimate each label pair's patch with its border locked; returns (faces, pairs).

    A patch may move at most ``max_error`` times the diagonal of the smaller part
    it bounds, the bound :func:`miss.decimate` gives each part on its own.
    """
    key = pairs[:, 0] * (int(pairs.max()) + 1) + pairs[:, 1]
    order = np.argsort(key, kind="stable")
    starts = np.flatnonzero(np.diff(key[order], prepend=-1))
    ends = np.append(starts[1:], len(order))
    diagonal = {label: mesh.diagonal() for label, mesh in full.items()}
    out_faces, out_pairs = [], []
    used = np.zeros(len(vertices), dtype=bool)  # scratch, reset after each patch
    for start, end in zip(starts, ends, strict=True):
        patch = faces[order[start:end]]
        pair = pairs[order[start]]
        bound = max_error * min(diagonal[int(x)] for x in pair if int(x) in diagonal)
        kept = _simplify_locked(vertices, patch, reduce, bound, used)
        out_faces.append(kept)
        out_pairs.append(np.repeat(pair[None, :], len(kept), axis=0))
    return np.concatenate(out_faces), np.concatenate(out_pairs)


def _simplify_locked(
    vertices: np.ndarray, faces: np.ndarray, reduce: float, bound_mm: float, used: np.ndarray
) -> np.ndarray:
    """meshoptimizer on one patch, border vertices locked, error in mm; indices into ``vertices``.

    The patch's vertices are copied out (meshoptimizer's cost grows with the whole
    vertex buffer it is given); ``used`` is an all-False scratch mask of len(vertices).
    """
    used[faces.ravel()] = True
    ids = np.flatnonzero(used)
    used[ids] = False
    indices = np.searchsorted(ids, faces.ravel()).astype(np.uint32)
    out = np.zeros_like(indices)
    target = max(3, int(round(len(indices) * (1.0 - reduce))) // 3 * 3)
    count = meshoptimizer.simplify(
        out, indices, np.ascontiguousarray(vertices[ids], dtype=np.float32),
        target_index_count=target, target_error=bound_mm,
        options=meshoptimizer.SIMPLIFY_LOCK_BORDER | meshoptimizer.SIMPLIFY_ERROR_ABSOLUTE,
    )  # fmt: skip
    if count == 0:
        return faces  # never let a small closed patch vanish
    return ids[out[:count].reshape(-1, 3)].astype(np.int32)


def _shared_result(
    full: Mesh,
    mesh: Mesh,
    label: int,
    reduce: float,
    error_bound: float,
    max_error: float,
    seconds: float,
    measure: bool,
) -> LabelSurface:
    """A part's patch-decimated surface with the report :func:`miss.decimate` would give."""
    report = DecimationReport(
        method="quadric",
        reduce=reduce,
        error_bound=error_bound,
        triangles_in=full.n_triangles,
        triangles_out=mesh.n_triangles,
        achieved_reduction=1.0 - mesh.n_triangles / max(full.n_triangles, 1),
        final_bound_mm=max_error * full.diagonal(),
        max_error_mm=None,
        mean_error_mm=None,
        seconds=seconds,
        measure_seconds=0.0,
        finished_with="quadric",
    )
    if measure:
        report = measured(report, full, mesh, MEASURE_SAMPLES)
    return LabelSurface(label, full, mesh, report)
