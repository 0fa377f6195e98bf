"""Connected components of a structure, found on the voxels (not on the mesh).

Voxels are grouped with 26-connectivity (faces, edges and corners touch). Two
groups are then never in the same marching cube, so extracting one group with
the others blanked out gives exactly its share of the full surface. Working on
voxels rather than on triangles also keeps a hollow structure (a skull with its
inner table) one part instead of an outer and an inner shell.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

import numpy as np

Components = Literal["all", "largest", "split"]

# scipy.ndimage (0.3 s to load) is imported by the functions that use it: a job that keeps
# every piece of its surfaces never loads it.
_CONNECTIVITY = np.ones((3, 3, 3), dtype=bool)  # 26 neighbours


@dataclass(frozen=True)
class Selection:
    """Components chosen from a mask.

    Attributes
    ----------
    labelled : (X, Y, Z) int32 array
        Component id per voxel (0 outside the mask).
    kept : list of int
        Ids of the chosen components, largest first.
    sizes : list of int
        Voxel counts of the kept components, same order.
    dropped : int
        Components left out (below the minimum size or past ``max_parts``).
    """

    labelled: np.ndarray
    kept: list[int]
    sizes: list[int]
    dropped: int


def select_components(
    mask: np.ndarray, components: Components | str, min_voxels: float, max_parts: int
) -> Selection:
    """Label the mask's components and choose them as ``components`` says.

    ``"all"`` keeps every component of at least ``min_voxels`` voxels,
    ``"largest"`` the largest one only, ``"split"`` the same set as ``"all"``
    (the caller makes each its own part); never more than ``max_parts``.
    """
    from scipy import ndimage

    labelled, count = ndimage.label(mask, structure=_CONNECTIVITY, output=np.int32)
    sizes = np.bincount(labelled.ravel(order="K"), minlength=count + 1)
    kept, dropped = choose_components(sizes, components, min_voxels, max_parts)
    return Selection(labelled, kept, [int(sizes[i]) for i in kept], dropped)


def choose_components(
    sizes: np.ndarray, components: Components | str, min_voxels: float, max_parts: int
) -> tuple[list[int], int]:
    """The ids to keep, largest first (ties: the lower id), and how many were left out.

    ``sizes`` : (count + 1,) int array, the voxel count of component ``i`` at ``i`` (ids
    numbered as ``scipy.ndimage.label`` numbers them; ``sizes[0]`` ignored). Shared by the
    in-memory and the blockwise (:mod:`miss.structures.block_components`) paths, so that
    both choose alike.
    """
    sizes = np.asarray(sizes).copy()
    count = len(sizes) - 1
    sizes[0] = 0
    order = np.argsort(-sizes[1:], kind="stable") + 1  # ids, largest first; ties by id
    big = [int(i) for i in order if sizes[i] >= max(min_voxels, 1)]
    limit = 1 if components == "largest" else max_parts
    kept = big[:limit]
    return kept, count - len(kept)


def relabel_components(
    data: np.ndarray,
    chosen: Iterable[int],
    components: Components | str,
    min_voxels: float,
    max_parts: int,
) -> tuple[np.ndarray, dict[int, tuple[int, int]], int]:
    """Apply the component choice to every chosen label of a label map.

    Parameters
    ----------
    data : (X, Y, Z) integer array
        The label map.
    chosen : labels to treat; other labels stay as they are (they are still
        neighbours whose boundaries the chosen ones share).

    Returns
    -------
    relabelled : (X, Y, Z) int32 array
        Dropped components set to 0 (background); with ``"split"`` every kept
        component after a label's largest gets a new id above the map's maximum.
    origin : dict of int to (label, rank)
        For every id to build a part from: its original label and its rank by
        size (0 = largest, the only rank unless split).
    dropped : int
        Components removed.
    """
    from scipy import ndimage

    out = np.array(data, dtype=np.int32, order="F")
    boxes = ndimage.find_objects(out)
    origin: dict[int, tuple[int, int]] = {}
    next_id, dropped = int(out.max(initial=0)) + 1, 0
    for label in chosen:
        box = boxes[label - 1] if label - 1 < len(boxes) else None
        if box is None:
            continue
        view = out[box]
        picked = select_components(view == label, components, min_voxels, max_parts)
        dropped += picked.dropped
        view[(view == label) & ~np.isin(picked.labelled, picked.kept)] = 0
        for rank, comp in enumerate(picked.kept):
            new_id = label
            if rank and components == "split":
                new_id, next_id = next_id, next_id + 1
                view[picked.labelled == comp] = new_id
            origin.setdefault(new_id, (label, rank))
    return out, origin, dropped
