"""2-D pictures of a volume: slice PNGs, thumbnails, the histogram and threshold presets.

Slices are shown the way radiologists read them: axial and coronal with the patient's
right on the screen's left, sagittal with anterior on the left, superior always up.
Which voxel axis runs where, and whether it is flipped, comes from the affine, so
RAS-stored NIfTI and LPS DICOM look the same. Pixels are resampled to square
millimetres so a 0.5 x 0.5 x 4 mm stack does not look squashed.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from typing import Any

import numpy as np
from PIL import Image

#: View name -> voxel axis held fixed (slices are taken along it).
AXES = {"sagittal": 0, "coronal": 1, "axial": 2}
#: LPS directions of the screen's right and down for each view.
_SCREEN = {
    "axial": ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0)),
    "coronal": ((1.0, 0.0, 0.0), (0.0, 0.0, -1.0)),
    "sagittal": ((0.0, 1.0, 0.0), (0.0, 0.0, -1.0)),
}
MAX_SIDE = 1024


THUMB_SIDE = 160
TINT = np.array([255.0, 96.0, 32.0], dtype=np.float32)
TINT_ALPHA = 0.55
HU_PRESETS = (("bone", 300.0), ("skin", -500.0))


def views(affine: np.ndarray, dims: tuple[int, int, int]) -> dict[str, dict[str, Any]]:
    """For each view: which voxel axes run across and down the image, flips, size in mm.

    ``horizontal``/``vertical`` are {"axis": 0|1|2, "flipped": bool}; flipped means the
    axis's index grows right-to-left (or bottom-to-top), e.g. slice numbers on sagittal.
    """
    out = {}
    spacing = np.linalg.norm(np.asarray(affine)[:3, :3], axis=0)
    for name, fixed in AXES.items():
        h, v = (a for a in range(3) if a != fixed)
        right, down = _SCREEN[name]
        out[name] = {
            "axis": fixed,
            "count": int(dims[fixed]),
            "horizontal": {"axis": h, "flipped": bool(np.dot(affine[:3, h], right) < 0)},
            "vertical": {"axis": v, "flipped": bool(np.dot(affine[:3, v], down) < 0)},
            "width_mm": float(dims[h] * spacing[h]),
            "height_mm": float(dims[v] * spacing[v]),
        }
    return out


def slice_plane(data: np.ndarray, view: dict[str, Any], index: int) -> np.ndarray:
    """The slice as a float32 (rows, columns) image in display orientation."""
    # basic indexing reads one plane of the memory map; np.take copied the whole volume
    # (29 MB, 100 ms for CThead) for every slice
    where: list[Any] = [slice(None)] * data.ndim
    where[view["axis"]] = index
    plane = np.asarray(data[tuple(where)], dtype=np.float32).T
    if view["vertical"]["flipped"]:
        plane = plane[::-1, :]
    if view["horizontal"]["flipped"]:
        plane = plane[:, ::-1]
    return plane


def display_size(view: dict[str, Any], shape: tuple[int, int], max_side: int) -> tuple[int, int]:
    """(width, height) in pixels with square millimetres, the finer axis kept at full detail."""
    rows, cols = shape
    w_mm, h_mm = view["width_mm"], view["height_mm"]
    px = min(w_mm / cols, h_mm / rows)
    width, height = w_mm / px, h_mm / px
    scale = min(1.0, max_side / max(width, height))
    return max(1, round(width * scale)), max(1, round(height * scale))


def render(
    plane: np.ndarray,
    size: tuple[int, int],
    window: float,
    level: float,
    threshold: float | None = None,
    overlay: np.ndarray | None = None,
) -> bytes:
    """PNG of a plane under window/level (units of the volume), voxels above ``threshold``
    tinted, then ``overlay`` ((rows, columns, 4): RGB 0-255 and alpha, e.g. a label map's
    colours) laid over it."""
    low = level - window / 2.0
    grey = np.clip((plane - low) * (255.0 / window), 0.0, 255.0)
    if threshold is None and overlay is None:  # one channel: a third of the work
        image = Image.fromarray(np.ascontiguousarray(grey.astype(np.uint8)), "L")
    else:
        rgb = np.repeat(grey[:, :, None], 3, axis=2)
        if threshold is not None:
            above = plane > threshold
            rgb[above] = (1.0 - TINT_ALPHA) * rgb[above] + TINT_ALPHA * TINT
        if overlay is not None:
            alpha = overlay[:, :, 3:]
            rgb = (1.0 - alpha) * rgb + alpha * overlay[:, :, :3]
        image = Image.fromarray(np.ascontiguousarray(rgb.astype(np.uint8)), "RGB")
    if image.size != size:
        image = image.resize(size, Image.Resampling.BILINEAR)
    buf = io.BytesIO()
    image.save(buf, "PNG", compress_level=3)
    return buf.getvalue()


def thumbnail(data: np.ndarray, affine: np.ndarray, window: dict[str, float]) -> bytes:
    """The middle axial slice, small, under the default window."""
    return thumbnail_of(data[:, :, data.shape[2] // 2], affine, data.shape, window)


def thumbnail_of(
    middle: np.ndarray,
    affine: np.ndarray,
    dims: tuple[int, int, int],
    window: dict[str, float],
) -> bytes:
    """:func:`thumbnail` from the middle axial plane, (X, Y), alone (ingestion streams)."""
    view = views(affine, dims)["axial"]
    plane = slice_plane(middle[:, :, None], view, 0)
    return render(
        plane, display_size(view, plane.shape, THUMB_SIDE), window["window"], window["level"]
    )


#: Histograms count at most this many voxels: every n-th slice of larger volumes.
SAMPLE_VOXELS = 1 << 25


def sample_step(dims: tuple[int, int, int]) -> int:
    """Which slices a histogram counts: every n-th one, so at most ``SAMPLE_VOXELS``."""
    return max(1, int(np.ceil(int(np.prod(dims)) / SAMPLE_VOXELS)))


def _sample(data: np.ndarray) -> np.ndarray:
    """Every n-th slice of very large volumes: histograms need counts, not every voxel."""
    return finite_values(np.asarray(data[:, :, :: sample_step(data.shape)]))


def finite_values(block: np.ndarray) -> np.ndarray:
    """The finite values of ``block``, flat."""
    return block[np.isfinite(block)] if block.dtype.kind == "f" else block.ravel()


def histogram(data: np.ndarray, bins: int = 256) -> dict[str, Any]:
    """Counts per value bin over the volume's range; integer data gets whole-number bins."""
    return histogram_of([_sample(data)], bins)


def histogram_of(parts: Sequence[np.ndarray], bins: int = 256) -> dict[str, Any]:
    """:func:`histogram` of values sampled already (flat, finite arrays of one dtype),
    counted part by part: no joined copy of a sample of up to ``SAMPLE_VOXELS``."""
    parts = [p for p in parts if p.size]
    lo, hi = min(float(p.min()) for p in parts), max(float(p.max()) for p in parts)
    if parts[0].dtype.kind in "iu" and hi - lo + 1 <= bins:
        edges = np.arange(lo, hi + 2, dtype=np.float64) - 0.5
    else:
        edges = np.linspace(lo, hi if hi > lo else lo + 1.0, bins + 1)
    # Each value falls in the same bin counted alone or with the others: sums are exact.
    start = np.zeros(len(edges) - 1, dtype=np.int64)  # histogram's counts
    counts = sum((np.histogram(p, bins=edges)[0] for p in parts), start)
    return {"edges": edges.tolist(), "counts": counts.tolist(), "range": [lo, hi]}


def percentile(hist: dict[str, Any], q: float, above: float | None = None) -> float:
    """Approximate q-th percentile (0..100) from histogram counts, optionally of values > above."""
    edges = np.asarray(hist["edges"])
    counts = np.asarray(hist["counts"], dtype=np.float64)
    if above is not None:
        counts = np.where(edges[:-1] >= above, counts, 0.0)
    cum = np.cumsum(counts)
    if cum[-1] == 0:
        return float(edges[-1])
    i = int(np.searchsorted(cum, cum[-1] * q / 100.0))
    return float((edges[i] + edges[i + 1]) / 2.0)


def default_window(hist: dict[str, Any]) -> dict[str, float]:
    """A window spanning the 0.5th..99.5th percentiles: every structure visible, none clipped."""
    lo, hi = percentile(hist, 0.5), percentile(hist, 99.5)
    if hi <= lo:
        lo, hi = hist["range"][0], max(hist["range"][1], hist["range"][0] + 1.0)
    return {"window": _round(hi - lo), "level": _round((hi + lo) / 2.0)}


def otsu(hist: dict[str, Any]) -> float:
    """Otsu's threshold: the split of the histogram with the largest between-class variance."""
    edges = np.asarray(hist["edges"])
    counts = np.asarray(hist["counts"], dtype=np.float64)
    centres = (edges[:-1] + edges[1:]) / 2.0
    w0 = np.cumsum(counts)
    w1 = w0[-1] - w0
    m0 = np.cumsum(counts * centres) / np.maximum(w0, 1e-12)
    m1 = (np.sum(counts * centres) - np.cumsum(counts * centres)) / np.maximum(w1, 1e-12)
    between = w0 * w1 * (m0 - m1) ** 2
    return float(edges[int(np.argmax(between[:-1])) + 1])


#: CT stored without its rescale (value = HU + 1024, e.g. CThead, VTK's headsq) shows soft
#: tissue (0..80 HU) as a narrow peak in this range; MR's tissue classes make a broad hump.
CT_OFFSET_PEAK = (1000.0, 1110.0)
#: The body's interquartile range over its median below this: a CT's soft-tissue peak
#: (0.09 on CThead and headsq; 0.21-0.46 on the MR scans in ../shared/datasets).
CT_PEAK_SPREAD = 0.15
#: What a level means, as the page labels its field.
DENSITY_HU, DENSITY, INTENSITY = "Density (HU)", "Density (CT value)", "Intensity"


def scale(hist: dict[str, Any], modality: str, units: str) -> dict[str, str]:
    """What a level of this volume measures: {"label": the form field's name, "kind": "CT"
    or "MR", "reason": how that was decided}. The header's modality and units decide; a
    file without them (NIfTI, NRRD, MetaImage) is CT when its body's values form the narrow
    soft-tissue peak of CT stored as HU + 1024, else taken as MR-like intensities."""
    if units == "HU":
        return {"label": DENSITY_HU, "kind": "CT", "reason": "values in Hounsfield units"}
    if modality.upper() == "CT":
        return {"label": DENSITY, "kind": "CT", "reason": "the header says CT"}
    if modality:
        return {"label": INTENSITY, "kind": "MR", "reason": f"the header says {modality}"}
    peak, spread = _body_peak(hist)
    lo, hi = CT_OFFSET_PEAK
    if hist["range"][0] > -1.0 and lo <= peak <= hi and spread < CT_PEAK_SPREAD:
        why = f"no modality in the file; soft tissue peaks at {peak:g}, as CT stored as HU + 1024"
        return {"label": DENSITY, "kind": "CT", "reason": why}
    why = "no modality in the file and no CT soft-tissue peak: taken as MR-like intensities"
    return {"label": INTENSITY, "kind": "MR", "reason": why}


def _body_peak(hist: dict[str, Any]) -> tuple[float, float]:
    """The most common value above the background (Otsu's split) and the body's spread:
    interquartile range over median."""
    edges = np.asarray(hist["edges"])
    counts = np.asarray(hist["counts"], dtype=np.float64)
    centres = (edges[:-1] + edges[1:]) / 2.0
    body = np.where(edges[:-1] >= otsu(hist), counts, 0.0)
    if body.sum() == 0:
        return float(centres[-1]), float("inf")
    q1, median, q3 = (percentile(hist, q, above=otsu(hist)) for q in (25.0, 50.0, 75.0))
    spread = (q3 - q1) / median if median > 0 else float("inf")
    return float(centres[int(np.argmax(body))]), spread


def presets(hist: dict[str, Any], units: str, modality: str = "") -> list[dict[str, Any]]:
    """Suggested levels, the default first. CT in HU: bone 300 / skin -500. Other CT (its
    values HU + 1024, or unscaled): the background/body split (Otsu) as skin and the 95th
    percentile of the body as bone. MR and intensities of unknown meaning: never "bone"
    (bone is dark on MR): skin, the background/body split, first (the outer surface, whole
    on a head), and tissue, the split of the body's own values into two classes."""
    lo, hi = hist["range"]
    if units == "HU":
        found = [{"name": n, "level": v, "basis": "HU"} for n, v in HU_PRESETS if lo < v < hi]
        if len(found) == len(HU_PRESETS):
            return found
    skin = otsu(hist)
    outer = {"name": "skin", "level": _round(skin), "basis": "Otsu split of background and body"}
    if scale(hist, modality, units)["kind"] == "CT":
        bone = percentile(hist, 95.0, above=skin)
        basis = "95th percentile above the skin level"
        return [{"name": "bone", "level": _round(bone), "basis": basis}, outer]
    tissue = otsu(_above(hist, skin))
    basis = "Otsu split of the body's values (above the skin level)"
    return [outer, {"name": "tissue", "level": _round(tissue), "basis": basis}]


def _above(hist: dict[str, Any], level: float) -> dict[str, Any]:
    """The histogram's bins from ``level`` up: the body's values without the background."""
    edges = np.asarray(hist["edges"])
    first = min(int(np.searchsorted(edges, level, side="right")) - 1, len(edges) - 3)
    first = max(first, 0)
    counts = np.asarray(hist["counts"])[first:]
    return {"edges": edges[first:].tolist(), "counts": counts.tolist(), "range": hist["range"]}


def _round(value: float) -> float:
    """Three significant digits: a level a person can type and read back."""
    if value == 0:
        return 0.0
    digits = 2 - int(np.floor(np.log10(abs(value))))
    return float(round(value, max(digits, 0)))
