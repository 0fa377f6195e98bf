"""``label_counts``: a label map's labels and voxel counts, None for an image; it gives
up on an image at the first slices that hold more values than a label map may."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from miss.structures.counts import label_counts
from miss.types import Volume


def _reference(data: np.ndarray, max_labels: int) -> dict[int, int] | None:
    """The whole volume counted at once."""
    if data.min() < 0 or data.max() > 65535:
        return None
    values, counts = np.unique(data, return_counts=True)
    if len(values) > max_labels + 1:
        return None
    return {int(v): int(n) for v, n in zip(values, counts, strict=True) if v != 0}


@settings(max_examples=60, deadline=None)
@given(
    shape=st.tuples(st.integers(1, 6), st.integers(1, 6), st.integers(1, 5)),
    spread=st.integers(1, 40),
    max_labels=st.integers(1, 12),
    seed=st.integers(0, 2**32 - 1),
    dtype=st.sampled_from([np.uint8, np.int16, np.uint16, np.int32]),
)
def test_counts_are_the_whole_volumes_counts(
    shape: tuple[int, int, int], spread: int, max_labels: int, seed: int, dtype: type
) -> None:
    data = np.random.default_rng(seed).integers(0, spread, size=shape).astype(dtype)
    assert label_counts(Volume(data=data, affine=np.eye(4)), max_labels) == _reference(
        data, max_labels
    )


def test_an_image_with_its_values_in_the_last_slice_only_is_an_image() -> None:
    """Giving up early must not make the cumulative count forget the last slices."""
    data = np.zeros((30, 30, 4), dtype=np.uint16)
    data[:, :, 3] = np.arange(900).reshape(30, 30)
    assert label_counts(Volume(data=data, affine=np.eye(4))) is None
    data[:, :, 3] = np.arange(900).reshape(30, 30) % 7
    assert label_counts(Volume(data=data, affine=np.eye(4))) == {
        v: int((data == v).sum()) for v in range(1, 7)
    }
