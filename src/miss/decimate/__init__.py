"""Decimation: fewer triangles within an error bound, behind one function.

Methods
-------
``schroeder``
    The paper's vertex decimation (Schroeder, Zarge & Lorensen 1992), ours, in
    :mod:`miss._schroeder`. Vertices are never moved and none are created.
``quadric``
    meshoptimizer's edge-collapse simplifier with quadric error metrics: the fast
    path and the web default. It also keeps a subset of the original vertices.
``none``
    The mesh as it is.

Both bounds are fractions of the mesh's bounding-box diagonal, as in the paper
(0.0002 and 0.002). The bound is raised until the reduce rate is met or
``max_error`` is reached. Every call reports the deviation it really caused, in mm.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Any, Literal

from miss.errors import BadParameter
from miss.spec import METHODS

if TYPE_CHECKING:
    from miss.types import Mesh

Method = Literal["none", "quadric", "schroeder"]
#: Points sampled on each surface to measure a decimation's deviation.
SAMPLES = 100_000


@dataclass(frozen=True)
class DecimationReport:
    """What a decimation did. Bounds are fractions of the diagonal; errors are measured, mm."""

    method: str
    reduce: float
    error_bound: float
    triangles_in: int
    triangles_out: int
    achieved_reduction: float
    final_bound_mm: float
    max_error_mm: float | None
    mean_error_mm: float | None
    seconds: float
    measure_seconds: float

    def to_dict(self) -> dict[str, object]:
        return asdict(self)

    def summary(self) -> dict[str, Any]:
        """What the CLI's ``--json`` and the API's stats say of a decimation."""
        return {
            "method": self.method,
            "reduce": self.reduce,
            "error_bound": self.error_bound,
            "triangles_before": self.triangles_in,
            "achieved_reduction": round(self.achieved_reduction, 4),
            "max_error_mm": self.max_error_mm,
            "mean_error_mm": self.mean_error_mm,
        }


def _check(method: str, reduce: float, error_bound: float, max_error: float) -> None:
    if method not in METHODS:
        raise BadParameter(
            f"unknown decimation method {method!r}; choose one of {', '.join(METHODS)}."
        )
    if not 0.0 <= reduce < 1.0:
        raise BadParameter(
            f"reduce must be a fraction of triangles to remove in [0, 1), got {reduce!r} (e.g. 0.9)."
        )
    if not 0.0 < error_bound <= max_error:
        raise BadParameter(
            f"error bound must be > 0 and <= the maximum error {max_error!r} "
            f"(fractions of the diagonal, e.g. 0.0002), got {error_bound!r}."
        )


def decimate(
    mesh: Mesh,
    method: Method | str = "quadric",
    reduce: float = 0.9,
    error_bound: float = 0.0002,
    *,
    max_error: float = 0.01,
    measure: bool = True,
    samples: int = SAMPLES,
    paper_passes: int = 0,
) -> tuple[Mesh, DecimationReport]:
    """Decimate ``mesh``; returns the new mesh and a report with the measured error.

    Parameters
    ----------
    mesh : Mesh
    method : "none", "quadric" or "schroeder"
    reduce : float
        Target fraction of triangles to remove, in [0, 1) (the paper's reduce rate).
    error_bound : float
        Starting local error bound, as a fraction of the bounding-box diagonal.
    max_error : float
        The bound is never raised past this fraction of the diagonal.
    measure : bool
        Measure the two-sided deviation from the input surface (mm), from
        ``samples`` points on each surface.
    paper_passes : int
        ``schroeder`` only: N > 0 runs the 1998 pipeline's schedule instead of raising the
        bound until the target is met: at most N whole passes at 1..N x ``error_bound``
        (vtkDecimate's iterations), the reduce target looked at between passes only.
    """
    _check(method, reduce, error_bound, max_error)
    if paper_passes and method != "schroeder":
        raise BadParameter(
            f"paper_passes is the schedule of the paper's own decimation; use method "
            f"'schroeder' with it, not {method!r}."
        )
    # The native libraries load on the first call, not with ``import miss``; the
    # measurement's (numba) only when measuring.
    from miss.decimate.quadric import quadric
    from miss.decimate.schroeder import schroeder
    from miss.geometry import compact, vertex_normals
    from miss.types import Mesh

    diag = mesh.diagonal()
    start = time.perf_counter()
    if method == "none" or mesh.n_triangles == 0:
        faces, final_mm = mesh.faces, 0.0
    elif method == "quadric":
        faces, rel = quadric(mesh, reduce, max_error)
        final_mm = rel * diag
    else:
        faces, final_mm = schroeder(
            mesh, reduce, error_bound * diag, max_error * diag, paper_passes
        )
    if method != "none":
        vertices, faces = compact(mesh.vertices, faces)
        out = Mesh(vertices=vertices, faces=faces, normals=vertex_normals(vertices, faces))
    else:
        out = mesh
    report = DecimationReport(
        method=method,
        reduce=reduce,
        error_bound=error_bound,
        triangles_in=mesh.n_triangles,
        triangles_out=out.n_triangles,
        achieved_reduction=1.0 - out.n_triangles / max(mesh.n_triangles, 1),
        final_bound_mm=final_mm,
        max_error_mm=0.0 if method == "none" else None,
        mean_error_mm=0.0 if method == "none" else None,
        seconds=time.perf_counter() - start,
        measure_seconds=0.0,
    )
    return out, measured(report, mesh, out, samples) if measure else report


def measured(
    report: DecimationReport, before: Mesh, after: Mesh, samples: int = SAMPLES
) -> DecimationReport:
    """``report`` with the two-sided deviation of ``after`` from ``before`` measured (mm),
    from ``samples`` points on each surface; a report already measured is returned as is.

    A job measures after its files are written (the viewer draws the model meanwhile):
    ``decimate(..., measure=False)`` now, this later.
    """
    if report.max_error_mm is not None:
        return report
    from miss.deviation import deviation

    start = time.perf_counter()
    dev = deviation(before, after, samples=samples)
    return replace(
        report,
        max_error_mm=dev.max_mm,
        mean_error_mm=dev.mean_mm,
        measure_seconds=time.perf_counter() - start,
    )
