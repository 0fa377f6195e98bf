"""What the pages need of a volume, gathered plane by plane while it is being stored.

Ingestion never holds a big volume whole (:mod:`miss.server.storage.chunked`), so the
value range, the provenance hash, the histogram's sample and the thumbnail's plane are
taken from the (X, Y) planes as they pass on their way to the disk.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from miss.server.volumes import imaging


@dataclass
class Summary:
    """Running figures of a volume of ``dims`` voxels whose planes pass through
    :meth:`watch` (z in order; ``dims`` = (X, Y, Z)), and its (4, 4) ``affine``."""

    dims: tuple[int, int, int]
    dtype: np.dtype
    affine: np.ndarray
    lo: float = float("inf")
    hi: float = float("-inf")
    planes: int = 0
    sample: list[np.ndarray] = field(default_factory=list)
    middle: np.ndarray | None = None
    _digest: Any = field(default_factory=hashlib.sha256)

    def watch(self, planes: Iterable[np.ndarray]) -> Iterator[np.ndarray]:
        """The planes, unchanged, each counted on its way."""
        step = imaging.sample_step(self.dims)
        for plane in planes:
            plane = np.asarray(plane, dtype=self.dtype)
            k = self.planes
            # (X, Y) transposed is x fastest: the bytes of the Fortran-order volume, z in
            # order, so the hash equals source_hash() of the whole array.
            self._digest.update(np.ascontiguousarray(plane.T).data)
            values = imaging.finite_values(plane)
            if values.size:
                self.lo, self.hi = (
                    min(self.lo, float(values.min())),
                    max(self.hi, float(values.max())),
                )
            if k % step == 0:
                # ravel copies a Fortran (X, Y) plane; a view would pin the caller's buffer
                self.sample.append(values if values.base is None else values.copy())
            if k == self.dims[2] // 2:
                self.middle = np.array(plane)
            self.planes += 1
            yield plane

    @property
    def source_sha256(self) -> str:
        """``ingest.source_hash`` of the volume: SHA-256 of its voxels, then its affine."""
        digest = self._digest.copy()
        digest.update(np.ascontiguousarray(self.affine, dtype="<f8").data)
        return digest.hexdigest()

    def histogram(self) -> dict[str, Any]:
        """``imaging.histogram`` of the volume, from the planes it samples."""
        return imaging.histogram_of(self.sample)

    def thumbnail(self, window: dict[str, float]) -> bytes:
        """``imaging.thumbnail`` of the volume, from its middle axial plane."""
        assert self.middle is not None, "the planes have not all passed yet"
        return imaging.thumbnail_of(self.middle, self.affine, self.dims, window)
