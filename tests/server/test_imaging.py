"""Slice images: one plane read straight from the (memory-mapped) volume."""

from __future__ import annotations

import numpy as np
import pytest

from miss.server.volumes.imaging import slice_plane


@pytest.mark.parametrize("axis", [0, 1, 2])
@pytest.mark.parametrize("flips", [(False, False), (True, False), (False, True)])
def test_slice_plane_is_the_plane_in_display_orientation(tmp_path, axis, flips) -> None:
    data = np.arange(5 * 6 * 7, dtype=np.int16).reshape((5, 6, 7), order="F")
    np.save(tmp_path / "v.npy", data)
    mapped = np.load(tmp_path / "v.npy", mmap_mode="r")
    view = {"axis": axis, "vertical": {"flipped": flips[0]}, "horizontal": {"flipped": flips[1]}}
    expected = np.take(data, 3, axis=axis).astype(np.float32).T
    if flips[0]:
        expected = expected[::-1, :]
    if flips[1]:
        expected = expected[:, ::-1]
    got = slice_plane(mapped, view, 3)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got, expected)
