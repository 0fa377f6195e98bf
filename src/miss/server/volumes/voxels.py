"""A stored volume as the browser's volume renderer takes it: block-mean downsampled to
a budget, 8-bit with its value mapping kept, one deflate-compressed body.

The body is a little-endian ``uint32`` header length, that many bytes of JSON (the
header: dims, the voxel-to-LPS affine of the sent grid, the value mapping ``real = a *
byte + b`` in the volume's units ...) and then the voxels, ``uint8``, i fastest
(``i + nx * (j + ny * k)``), which is the order a WebGL ``Data3DTexture`` reads. The
whole body is gzip-compressed once and sent with ``Content-Encoding: gzip``: a browser
inflates it on the way in, without a line of our code.

Stored volumes never change, so neither does this body: its URL is immutable.
"""

from __future__ import annotations

import gzip
import json
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np

from miss.server.volumes import imaging

#: The format of the body; a change to it changes the ETag, so caches never mix them.
VERSION = 1
#: Level 0, the first picture: no axis longer than this many voxels.
FIRST_SIDE = 256
#: Levels a viewer may ask for: 0 (first picture), 1 (full resolution within the budget).
LEVELS = (0, 1)
#: Percentiles of the histogram the 8 bits span: the odd hot pixel (metal, noise) must
#: not take the steps that soft tissue needs.
LOW_Q, HIGH_Q = 0.1, 99.9
#: Voxels read and averaged at once along k: bounds the float copy held in memory.
SLAB_VOXELS = 16 * 2**20


@dataclass(frozen=True)
class Mapping:
    """``real = scale * byte + offset`` (volume units: HU for CT); bytes 0..255."""

    scale: float
    offset: float

    def to_bytes(self, values: np.ndarray) -> np.ndarray:
        """Values (any shape, volume units) as the nearest byte, clipped to 0..255."""
        steps = np.rint((np.asarray(values, dtype=np.float32) - self.offset) / self.scale)
        return np.clip(steps, 0, 255).astype(np.uint8)


def mapping(hist: dict[str, Any]) -> Mapping:
    """The 8-bit mapping over the stored histogram's ``LOW_Q``..``HIGH_Q`` percentiles
    (the whole range when those meet, e.g. a two-valued volume)."""
    lo, hi = imaging.percentile(hist, LOW_Q), imaging.percentile(hist, HIGH_Q)
    if hi <= lo:
        lo, hi = float(hist["range"][0]), float(hist["range"][1])
    lo, hi = min(lo, hist["range"][1]), max(hi, lo + 1e-6)
    return Mapping(scale=(hi - lo) / 255.0, offset=lo)


def factors(dims: tuple[int, int, int], level: int, budget_bytes: int) -> tuple[int, int, int]:
    """The block size along each axis for ``level``.

    Level 0 shrinks each axis on its own to at most ``FIRST_SIDE`` (a 0.4 x 0.4 x 1.5 mm
    MR head of 512 x 512 x 120 becomes 256 x 256 x 120, its thin axis kept); level 1 is
    full resolution, or the same factor on every axis, the smallest that fits
    ``budget_bytes`` at one byte a voxel.
    """
    if level == 0:
        return tuple(max(1, math.ceil(d / FIRST_SIDE)) for d in dims)  # type: ignore[return-value]
    f = 1
    while math.prod(math.ceil(d / f) for d in dims) > max(budget_bytes, 1):
        f += 1
    return (f, f, f)


def block_mean(data: Any, f: tuple[int, int, int]) -> np.ndarray:
    """(ceil(X/fx), ceil(Y/fy), ceil(Z/fz)) float32 means of ``f``-sized blocks of ``data``
    (an (X, Y, Z) array or lazy zarr array), read a slab of k at a time; a block cut
    short by the edge averages the voxels it has."""
    nx, ny, nz = data.shape
    out = np.empty([math.ceil(n / s) for n, s in zip(data.shape, f, strict=True)], np.float32)
    per_k = max(f[2], (SLAB_VOXELS // max(nx * ny, 1)) // f[2] * f[2])
    for k0 in range(0, nz, per_k):
        slab = np.asarray(data[:, :, k0 : k0 + per_k], dtype=np.float32)
        out[:, :, k0 // f[2] : (k0 + slab.shape[2] + f[2] - 1) // f[2]] = _mean(slab, f)
    return out


def _mean(slab: np.ndarray, f: tuple[int, int, int]) -> np.ndarray:
    """Block means of one slab: ``np.add.reduceat`` along each axis, divided by the counts
    (edge blocks hold fewer voxels)."""
    for axis, step in enumerate(f):
        if step == 1:
            continue
        starts = np.arange(0, slab.shape[axis], step)
        counts = np.diff(np.append(starts, slab.shape[axis])).astype(np.float32)
        shape = [1, 1, 1]
        shape[axis] = len(starts)
        slab = np.add.reduceat(slab, starts, axis=axis) / counts.reshape(shape)
    return slab


def grid_affine(affine: np.ndarray, f: tuple[int, int, int]) -> np.ndarray:
    """The (4, 4) voxel-to-LPS affine of the block grid: steps ``f`` times longer, voxel
    (0, 0, 0) at the centre of the first block."""
    out = np.array(affine, dtype=np.float64)
    steps = np.asarray(f, dtype=np.float64)
    out[:3, 3] = affine[:3, 3] + affine[:3, :3] @ ((steps - 1) / 2)
    out[:3, :3] = affine[:3, :3] * steps
    return out


def encode(data: Any, affine: np.ndarray, info: dict[str, Any], hist: dict[str, Any],
           level: int, budget_bytes: int) -> bytes:  # fmt: skip
    """The gzip-compressed body (see the module's docstring) of one ``level``."""
    dims = tuple(int(n) for n in data.shape)
    f = factors(dims, level, budget_bytes)  # type: ignore[arg-type]
    means = block_mean(data, f)
    m = mapping(hist)
    header = {
        "version": VERSION,
        "level": level,
        "dims": list(means.shape),
        "dtype": "uint8",
        "order": "i fastest: index = i + nx * (j + ny * k)",
        "affine": grid_affine(affine, f).tolist(),
        "factors": list(f),
        "source_dims": list(dims),
        "scale": m.scale,
        "offset": m.offset,
        "units": info.get("units", ""),
        "modality": info.get("modality", ""),
        "window": info.get("window"),
        "range": hist["range"],
    }
    text = json.dumps(header).encode("utf-8")
    voxels = m.to_bytes(means).tobytes(order="F")
    body = struct.pack("<I", len(text)) + text + voxels
    # Level 6: within a few per cent of 9's size at a third of its time (CThead).
    return gzip.compress(body, compresslevel=6, mtime=0)


def decode(body: bytes) -> tuple[dict[str, Any], np.ndarray]:
    """The header and the (X, Y, Z) uint8 voxels of an uncompressed body (tests, tools)."""
    (n,) = struct.unpack_from("<I", body)
    header = json.loads(body[4 : 4 + n])
    flat = np.frombuffer(body, dtype=np.uint8, offset=4 + n)
    return header, flat.reshape(header["dims"], order="F")
