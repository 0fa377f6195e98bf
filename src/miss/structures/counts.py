"""Which labels a label map holds, and how many voxels each: numpy only, so that
``miss info`` and a label check need none of the surface libraries."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from miss.types import Volume

#: More distinct values than this and a volume is an image, not a label map.
MAX_LABELS = 512


def label_counts(volume: Volume, max_labels: int = MAX_LABELS) -> dict[int, int] | None:
    """Voxel count per label (0, the background, left out), or None for a non-label volume.

    A label map here is an integer volume with values in 0..65535 and at most
    ``max_labels`` distinct values; float volumes are images.
    """
    data = volume.data
    if not np.issubdtype(data.dtype, np.integer) or data.size == 0:
        return None
    lo, hi = int(data.min()), int(data.max())
    if lo < 0 or hi > 65535:
        return None
    # Slice by slice: bincount casts to int64, and a whole-volume cast is 10x slower. An
    # image is known as one at its first slices with more values than a label map has.
    counts = np.zeros(hi + 1, dtype=np.int64)
    for k in range(data.shape[2]):
        counts += np.bincount(data[:, :, k].ravel(order="K"), minlength=hi + 1)
        if np.count_nonzero(counts) > max_labels + 1:
            return None
    present = np.flatnonzero(counts)
    return {int(label): int(counts[label]) for label in present if label != 0}
