"""Decimation: fewer triangles within an error bound, behind one function.

Methods
-------
``schroeder``
    The paper's vertex decimation (Schroeder, Zarge & Lorensen 1992), ours, in
    :mod:`miss.decimate._schroeder`. Vertices are never moved and none are created.
``quadric``
    meshoptimizer's edge-collapse simplifier with quadric error metrics: the fast
    path and the web default. It also keeps a subset of the original vertices.
``collapse``
    Half-edge collapses, cheapest first by quadric error, each within a proven bound:
    ours, in :mod:`miss.decimate._collapse` (the same bound as schroeder's, for the fan
    from the vertex that stays). Vertices are never moved and none are created; it keeps
    fewer triangles than schroeder at the same bound (measured: ``benchmarks/collapse.py``).
``placed``
    Edge collapses whose kept vertex moves to where the quadric puts it, each within a
    proven bound: ours, native (:mod:`miss.decimate.placed`; the same overlay bound,
    carried over to an edge's two fans). The only bounded method that moves vertices: the
    fewest triangles at a bound, for the most time (measured: ``benchmarks/collapse.py``).
``none``
    The mesh as it is.

``error_bound`` is a fraction of the mesh's bounding-box diagonal, as in the paper
(0.0002, 0.002), and the contract is the same for every method: the output deviates from
the input surface by at most that bound, two-sided, in mm (measured, not estimated), and
``reduce`` is the target; decimation stops at whichever comes first, and the report says
which (``stopped_by``).

Schedules
---------
``guaranteed`` (default)
    The bound is a hard cap, and schroeder makes the model whichever method was asked for
    but collapse and placed, which hold it the same way (``finished_with`` says so): its triangles carry the error already spent on them
    (accumulated error), and each deletion's share is a bound on the distance between the
    triangles it removes and those that replace it, everywhere on them
    (:func:`miss.decimate._fan.overlay_gap`), so the output is within the bound everywhere,
    not only where it is measured. quadric's target error is an estimate no check at
    points can turn into a bound. Every run is also checked
    (:func:`miss.measure.bound_check`: every dropped input vertex to the output, every
    new output edge's middle to the input, and for quadric's models every new triangle's
    centroid too); a few input vertices out of
    bound are put back (:func:`_put_back`) and the result checked again; otherwise the
    region out of bound is locked and the run repeated (after seven runs the input is
    kept), so the bound reported as held was measured to hold as well.
``paper``
    The 1998 pipeline's: the bound is raised up to ``max_error`` until ``reduce`` is met
    (or ``paper_passes`` whole passes at 1..N x the bound). The report gives the bound it
    ended at, and the same check holds the output within that: schroeder's everywhere, as
    above; quadric's (five runs, each screened, before schroeder takes over) at the
    checked points only.
"""

from __future__ import annotations

import contextlib
import math
import numbers
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Any, Literal, get_args

from miss.errors import BadParameter

if TYPE_CHECKING:
    from concurrent.futures import Future, ThreadPoolExecutor

    import numpy as np

    from miss.measure import BoundCheck, Side
    from miss.measure.measurer import RemoteSide
    from miss.types import Mesh

Method = Literal["none", "quadric", "schroeder", "collapse", "placed"]
Schedule = Literal["guaranteed", "paper"]
#: The decimation methods, ``Method``'s (the job declaration, :mod:`miss.spec`, offers these).
METHODS: tuple[str, ...] = get_args(Method)
#: How a bound is held, ``Schedule``'s: as a hard cap (measured), or raised as the 1998
#: pipeline did.
SCHEDULES: tuple[str, ...] = get_args(Schedule)
# The defaults of a decimation, each once: :func:`decimate`'s and the job declaration's
# (:class:`miss.spec.Decimation`, which the REST API and the command line are made from).
#: The method: meshoptimizer's, the fast one.
METHOD: Method = "quadric"
#: The target fraction of triangles removed.
REDUCE = 0.9
#: The error bound, a fraction of the bounding-box diagonal (0.7 mm on a head CT).
ERROR_BOUND = 0.002
#: ``paper`` only: the most the bound is raised to, a fraction of the diagonal.
MAX_ERROR = 0.01
#: How the bound is held.
SCHEDULE: Schedule = "guaranteed"
#: Points sampled on each surface by :func:`measured` (a decimation's own check samples
#: nothing: see :func:`miss.measure.bound_check`).
SAMPLES = 100_000
#: Runs a decimation gets to come within its bound (the last one keeps the input).
ROUNDS = 8
# Each repeated quadric run aims this much lower: meshoptimizer's error is an estimate, and
# locking the regions out of bound alone moves the excess next door (measured on CThead).
_QUADRIC_TIGHTER = 0.7
# Quadric runs under the paper's schedule before a bound still not held is left to
# schroeder (whose accumulated error holds it): at tight bounds (CThead bone at 0.0002)
# seven quadric runs did not converge and the input came back whole, and where they did,
# with more triangles than schroeder's; the paper's loose raised bound took quadric five.
# Under the guaranteed schedule quadric does not run at all (see _runner): a first run
# there held none of benchmarks/bounds.py's 15 bounds at the checked points (2.4-3.5x over
# on CThead), and one that did would still be held only at those points.
_QUADRIC_ROUNDS = {"paper": 5}
# Input vertices out of bound that may be put back into an output (see _put_back), and
# how far inside its triangle (barycentric) each one's foot must fall.
_PUT_BACK = 64
_PUT_BACK_MARGIN = 0.01
# Input vertices a quadric run is screened at before the method hands over (see _strays).
_SCREEN = 2048
# Measured points within this fraction of the diagonal over the bound are round-off.
_TOLERANCE = 1e-6
# The methods whose models are within their bound by construction (the accumulated
# error, see miss.decimate._fan.overlay_gap): checked at the contract's points only.
_BOUNDED = ("schroeder", "collapse", "placed")


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
    schedule: str = "paper"
    bound_mm: float | None = None
    stopped_by: str | None = None
    bound_held: bool | None = None
    rounds: int = 1
    finished_with: str | None = None

    def to_dict(self) -> dict[str, object]:
        """Every field, by name."""
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
            "schedule": self.schedule,
            "bound_mm": self.bound_mm,
            "stopped_by": self.stopped_by,
            "bound_held": self.bound_held,
            # the method that made the model: under the guaranteed schedule schroeder's,
            # whatever was asked for; "none" when the input was kept whole
            "finished_with": self.finished_with or self.method,
        }


def check_decimation(
    method: str, error_bound: float, reduce: float, max_error: float, schedule: str
) -> None:
    """Refuse decimation parameters no run can take, with the fix: the one check of
    :func:`decimate` and of the job declaration (:class:`miss.spec.Decimation`, whose form
    names the messages use: ``decimate`` is the method)."""
    if method not in METHODS:
        raise BadParameter(f"decimate must be one of {', '.join(METHODS)}, got {method!r}.")
    if schedule not in SCHEDULES:
        raise BadParameter(f"schedule must be one of {', '.join(SCHEDULES)}, got {schedule!r}.")
    for name, value in (("error_bound", error_bound), ("reduce", reduce), ("max_error", max_error)):
        # numbers' ABC, not numpy's types: the command line checks a job without numpy
        real = isinstance(value, numbers.Real) and not isinstance(value, bool)
        if not real or not math.isfinite(value):
            raise BadParameter(f"{name} must be a number, got {value!r}.")
    if not 0.0 <= reduce < 1.0:
        raise BadParameter(
            f"reduce must be in [0, 1) (fraction removed, e.g. 0.9), got {reduce!r}."
        )
    cap = max_error if schedule == "paper" else math.inf
    if not 0.0 < error_bound <= cap:
        raise BadParameter(
            f"error_bound must be > 0 (and <= max_error {max_error!r} with schedule "
            f"'paper'), got {error_bound!r}."
        )


def decimate(
    mesh: Mesh,
    method: Method | str = METHOD,
    reduce: float = REDUCE,
    error_bound: float = ERROR_BOUND,
    *,
    max_error: float = MAX_ERROR,
    measure: bool = True,
    samples: int = SAMPLES,
    paper_passes: int = 0,
    schedule: Schedule | str = SCHEDULE,
    progress: Heard | None = None,
) -> tuple[Mesh, DecimationReport]:
    """Decimate ``mesh``; returns the new mesh and a report with the measured error.

    Parameters
    ----------
    mesh : Mesh
    method : "none", "quadric", "schroeder", "collapse" or "placed"
    reduce : float
        Target fraction of triangles to remove, in [0, 1) (the paper's reduce rate).
    error_bound : float
        The bound, a fraction of the bounding-box diagonal: the most the output may deviate
        from the input surface (two-sided, measured) under the ``guaranteed`` schedule; the
        starting bound under ``paper``.
    max_error : float
        ``paper`` only: the bound is never raised past this fraction of the diagonal.
    measure : bool
        Check the result (see :func:`miss.measure.bound_check`) and hold it within the
        bound; False leaves it unchecked (``bound_held`` None), for quick previews only.
    samples : int
        Unused by the check (kept for callers that pass it; :func:`measured` samples).
    paper_passes : int
        ``schroeder`` under ``paper`` only: N > 0 runs the 1998 pipeline's schedule: at most
        N whole passes at 1..N x ``error_bound`` (vtkDecimate's iterations), the reduce
        target looked at between passes only.
    schedule : "guaranteed" or "paper"
        See the module's docstring.
    progress : callable, optional
        ``progress(stage, fraction)``: ``("decimate", 0..1)`` as the removal goes (after
        each of schroeder's passes), ``("check", 0 or 1)`` around each check of the bound.
    """
    check_decimation(method, error_bound, reduce, max_error, schedule)
    if paper_passes and (method != "schroeder" or schedule != "paper"):
        raise BadParameter(
            f"paper_passes is the schedule of the paper's own decimation; use method "
            f"'schroeder' with schedule 'paper', not {method!r} with {schedule!r}."
        )
    # The native libraries load on the first call, not with ``import miss``; the
    # measurement's (numba) only when measuring.
    from miss.geometry import compact, vertex_normals
    from miss.types import Mesh

    start = time.perf_counter()
    if method == "none" or mesh.n_triangles == 0:
        faces, bound_mm, check, rounds, by, moved = mesh.faces, 0.0, None, 0, "none", None
    else:
        heard = progress or _unheard
        run = _runner(
            mesh, method, reduce, error_bound, max_error, paper_passes, schedule, checked=measure,
            heard=heard,
        )  # fmt: skip
        heard("decimate", 0.0)
        if measure:
            faces, bound_mm, check, rounds, by, moved = _held(mesh, run, heard=heard)
        else:
            (faces, bound_mm, by, moved), check, rounds = run(None, 1), None, 1
    if method != "none":
        kept = mesh.vertices if moved is None else moved.astype(mesh.vertices.dtype)
        vertices, faces = compact(kept, faces)
        out = Mesh(vertices=vertices, faces=faces, normals=vertex_normals(vertices, faces))
    else:
        out = mesh
    seconds = time.perf_counter() - start
    target = math.floor(mesh.n_triangles * (1.0 - reduce) + 1e-9)
    report = DecimationReport(
        method=method,
        reduce=reduce,
        error_bound=error_bound,
        triangles_in=mesh.n_triangles,
        triangles_out=out.n_triangles,
        achieved_reduction=1.0 - out.n_triangles / max(mesh.n_triangles, 1),
        final_bound_mm=bound_mm,
        max_error_mm=0.0 if check is None and method == "none" else None,
        mean_error_mm=0.0 if check is None and method == "none" else None,
        seconds=seconds - (check[1] if check else 0.0),
        measure_seconds=check[1] if check else 0.0,
        schedule=schedule,
        bound_mm=bound_mm,
        stopped_by="reduce" if out.n_triangles <= target else "bound",
        bound_held=True if method == "none" else None,
        rounds=rounds,
        finished_with=by,
    )
    if check is not None:
        report = replace(
            report, max_error_mm=check[0].max_mm, mean_error_mm=check[0].mean_mm, bound_held=True
        )
    return out, report


#: A progress callback: ``(stage, fraction 0..1 of that stage)``.
Heard = Callable[[str, float], None]


def _unheard(stage: str, fraction: float) -> None:
    return None


#: One run given the vertices locked and the round (1, 2, ...): (faces, bound mm, the
#: method that made them, and the vertices where the method moved some (None: the input's)).
Run = Callable[["np.ndarray | None", int], tuple["np.ndarray", float, str, "np.ndarray | None"]]


def _runner(
    mesh: Mesh,
    method: str,
    reduce: float,
    error_bound: float,
    max_error: float,
    paper_passes: int,
    schedule: str,
    fixed: np.ndarray | None = None,
    checked: bool = True,
    heard: Heard = _unheard,
) -> Run:
    """One run of ``method`` given the vertices locked: (faces kept, the bound it is held
    to, mm, the method that ran). Quadric runs after its first ``_QUADRIC_ROUNDS`` under
    the paper's schedule are schroeder's, held to the same bound; under the guaranteed
    schedule every run is schroeder's, but for ``checked`` False (a quick preview, held to
    nothing: one quadric run, as asked). ``heard`` hears ("decimate", fraction) after each
    of schroeder's passes and once a quadric run is done."""
    from miss.decimate.quadric import quadric
    from miss.decimate.schroeder import schroeder
    from miss.types import column_bounds

    diag = mesh.diagonal()
    bound_mm = (error_bound if schedule == "guaranteed" else max_error) * diag

    def tick(fraction: float) -> None:
        heard("decimate", fraction)

    if method == "quadric" and (schedule != "guaranteed" or not checked):
        # meshoptimizer's error is relative to the mesh's extent (its largest side)
        lo, hi = column_bounds(mesh.vertices)
        extent = max(float((hi - lo).max()), 1e-12)

        runs = _QUADRIC_ROUNDS.get(schedule, 1)

        def run_quadric(
            locked: np.ndarray | None, round_: int
        ) -> tuple[np.ndarray, float, str, None]:
            if round_ > runs:
                # quadric's locks are not schroeder's: its first run starts free (bar ``fixed``)
                free = fixed if round_ == runs + 1 else locked
                faces, ended = schroeder(mesh, reduce, bound_mm / 8, bound_mm, 0, free, tick)
                return faces, ended, "schroeder", None
            target = bound_mm / extent * _QUADRIC_TIGHTER ** (round_ - 1)
            faces = quadric(mesh, reduce, target, locked)[0]
            tick(1.0)  # meshoptimizer's one call says nothing on its way
            return faces, bound_mm, "quadric", None

        run_quadric.hands_over_after = runs  # type: ignore[attr-defined]
        return run_quadric
    if method in ("collapse", "placed"):
        return _collapse_runner(mesh, method, reduce, error_bound, max_error, schedule, diag)
    if schedule == "guaranteed":
        # Whatever the method asked for: schroeder's accumulated error is a bound (see
        # miss.decimate._fan.overlay_gap), quadric's error an estimate that a check at points
        # cannot make one (it held none of benchmarks/bounds.py's 15 bounds even there).
        # A rising bound spends the budget on the cheapest deletions first: b/8, b/4, b/2,
        # b; the run is held to b, the bound asked for, wherever the target stopped it.
        return lambda locked, _: (
            schroeder(mesh, reduce, bound_mm / 8, bound_mm, 0, locked, tick)[0],
            bound_mm,
            "schroeder",
            None,
        )
    return lambda locked, _: (
        *schroeder(mesh, reduce, error_bound * diag, max_error * diag, paper_passes, locked, tick),
        "schroeder",
        None,
    )


def _collapse_runner(
    mesh: Mesh,
    method: str,
    reduce: float,
    error_bound: float,
    max_error: float,
    schedule: str,
    diag: float,
) -> Run:
    """collapse's and placed's runs: held to the bound asked for (``guaranteed``), or,
    under ``paper``, at a bound doubled from ``error_bound`` up to ``max_error`` until
    ``reduce`` is met, as schroeder's passes (each stage goes on from the last, its
    triangles carrying their error)."""
    from miss.decimate.collapse import STAGES, collapse
    from miss.decimate.placed import placed

    def run(locked: np.ndarray | None, bound_mm: float, stages: tuple[float, ...]) -> tuple:
        if method == "placed":
            vertices, faces, ended = placed(mesh, reduce, bound_mm, locked, stages)
            # in the input's type, as the model will have them: the check measures those
            return faces, ended, "placed", vertices.astype(mesh.vertices.dtype)
        return (*collapse(mesh, reduce, bound_mm, locked, stages), "collapse", None)

    if schedule == "guaranteed":

        def held(locked: np.ndarray | None, _: int) -> tuple:
            faces, _ended, by, vertices = run(locked, error_bound * diag, STAGES)
            return faces, error_bound * diag, by, vertices  # held to the bound asked for

        return held
    stages = [error_bound]
    while stages[-1] < max_error:
        stages.append(min(2.0 * stages[-1], max_error))
    fractions = tuple(s / max_error for s in stages)
    return lambda locked, _: run(locked, max_error * diag, fractions)


def decimate_held(
    mesh: Mesh, method: Method | str, reduce: float, bound_mm: float, fixed: np.ndarray
) -> tuple[np.ndarray, np.ndarray, BoundCheck]:
    """The vertices (the input's, with those the method moved where it moved them) and
    the faces a ``guaranteed`` decimation of ``mesh`` keeps, with the ``fixed`` (N,)
    vertices never removed nor moved, and its check: measured within ``bound_mm`` (mm).
    For one block of a surface (its border fixed, so that the blocks still meet); the
    caller compacts. ``decimate`` is the whole-mesh function."""
    check_decimation(method, 1.0, reduce, 1.0, "guaranteed")
    diag = mesh.diagonal()
    if method == "none" or mesh.n_triangles == 0 or diag <= 0.0:
        run: Run = lambda locked, _: (mesh.faces, bound_mm, "none", None)  # noqa: E731
    else:
        run = _runner(mesh, method, reduce, bound_mm / diag, 1.0, 0, "guaranteed", fixed)
    faces, _, (check, _), _, _, moved = _held(mesh, run, fixed=fixed)
    return (mesh.vertices if moved is None else moved), faces, check


def _held(
    mesh: Mesh,
    run: Run,
    rounds: int = ROUNDS,
    fixed: np.ndarray | None = None,
    heard: Heard = _unheard,
) -> tuple[np.ndarray, float, tuple[BoundCheck, float], int, str, np.ndarray | None]:
    """Run until the output is measured within its bound: each time it is not, the input
    vertices around the points out of bound are locked and the run repeated (the locks
    start again, from ``fixed``, when another method takes over); the last round keeps the
    input as it is (0 mm). Returns (faces, bound mm, (check, seconds of checking), rounds
    run, the method that made the faces, the vertices where it moved some or None)."""
    from miss.measure import surface_adjacency, surface_grid

    def build() -> tuple[tuple, tuple[np.ndarray, np.ndarray]]:
        # the input's cells, searched in every round's check, and its triangles around each
        # vertex (those need no measuring)
        return surface_grid(mesh), surface_adjacency(mesh)

    def prepare() -> tuple[tuple, tuple[np.ndarray, np.ndarray]]:
        # at the lowest priority, so that it takes a core the run leaves idle (its last,
        # whole-mesh phase), not one the run uses; its kernels hold no lock
        _idle_priority()
        return build()

    from concurrent.futures import ThreadPoolExecutor

    # Made while the first round runs; only the wait for it, if any, counts as checking.
    pool = ThreadPoolExecutor(max_workers=1)
    making = pool.submit(prepare)
    made: list[tuple[tuple, tuple[np.ndarray, np.ndarray]]] = []

    def inputs() -> tuple[tuple, tuple[np.ndarray, np.ndarray]]:
        # the thread's, if it is done; else made here and now: on a machine busy with other
        # work a thread at nice 19 may not get a core for a long while
        if not made:
            made.append(making.result() if making.done() else build())
        return made[0]

    try:
        return _rounds(mesh, run, rounds, fixed, inputs, heard)
    finally:
        pool.shutdown(wait=False, cancel_futures=True)


def measuring_later(before: Mesh, samples: int, pool: ThreadPoolExecutor) -> Future[Side]:
    """Start the half of :func:`measured` that needs only ``before`` (its sample points and
    grid, :func:`miss.measure.side_of`) on ``pool``'s thread at the lowest priority, for
    a job that decimates ``before`` unmeasured and measures the result after: it is made
    meanwhile, on the core a quadric decimation (one thread) leaves idle."""
    # numpy's random generator, which the samples are drawn with, imported here: its first
    # import (13-17 ms of bytecode) on the thread at nice 19 held the GIL there, and the
    # decimation, on cores the thread hardly got, waited for it (a fresh `miss convert
    # --measure` of the MR head decimated in 0.082 s so, 0.057 s with this: 11 runs each)
    import numpy.random  # noqa: F401

    def make() -> Side:
        _idle_priority()
        from miss.measure import side_of

        return side_of(before, samples)

    return pool.submit(make)


def _idle_priority() -> None:
    """This thread at nice 19, where the system allows it (Linux: a thread's own nice).
    Threads it starts after would inherit it: the work it does (a side's sampling and grid,
    serial kernels) starts none."""
    import os
    import threading

    with contextlib.suppress(AttributeError, OSError):
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)


def _rounds(
    mesh: Mesh,
    run: Run,
    rounds: int,
    fixed: np.ndarray | None,
    inputs: Callable[[], tuple[tuple, tuple[np.ndarray, np.ndarray]]],
    heard: Heard = _unheard,
) -> tuple[np.ndarray, float, tuple[BoundCheck, float], int, str, np.ndarray | None]:
    """:func:`_held`'s rounds; ``inputs()``: the input's grid and adjacency; ``heard``
    hears ("check", 0) as each round's check of the bound begins, ("check", 1) at its end."""
    import numpy as np

    from miss.measure import bound_check

    fixed = np.zeros(mesh.n_vertices, dtype=bool) if fixed is None else fixed.astype(bool)
    locked = fixed.copy()
    spent, last = 0.0, ""
    slack = _TOLERANCE * mesh.diagonal()
    for round_ in range(1, rounds + 1):
        if round_ < rounds:
            faces, bound_mm, by, moved = run(locked, round_)
        else:
            faces, by, moved = mesh.faces, "none", None
        begin = time.perf_counter()
        if round_ == getattr(run, "hands_over_after", 0) and _strays(mesh, faces, bound_mm + slack):
            # the next round is another method's, which starts from ``fixed``: no locks wanted
            spent += time.perf_counter() - begin
            last = by
            continue
        heard("check", 0.0)
        grid, around = inputs()
        # past twice the bound only "out of bound" matters, not by how much; a model
        # schroeder made is within its bound by construction: measured at the contract's
        # points, not at its triangles' centroids too (see bound_check)
        cap, centroids = 2.0 * bound_mm + slack, by not in _BOUNDED
        check = bound_check(mesh, faces, cap, grid, around, centroids, moved)
        spent += time.perf_counter() - begin
        heard("check", 1.0)
        if check.max_mm <= bound_mm + slack or round_ == rounds:
            return faces, bound_mm, (check, spent), round_, by, moved
        begin = time.perf_counter()
        # (an output that moved vertices is run again instead: the splits assume they are
        # the input's)
        mended = None if moved is not None else _put_back(mesh, faces, check, bound_mm + slack)
        again = None
        if mended is not None:
            again = bound_check(mesh, mended, cap, grid, around, centroids)
        spent += time.perf_counter() - begin
        if mended is not None and again is not None and again.max_mm <= bound_mm + slack:
            return mended, bound_mm, (again, spent), round_, by, None
        if by != last and last:
            locked[:] = fixed
        locked |= _out_of_bound(mesh, check, bound_mm)
        last = by
    raise AssertionError("unreachable: the last round keeps the input")


def _put_back(
    mesh: Mesh, faces: np.ndarray, check: BoundCheck, limit_mm: float
) -> np.ndarray | None:
    """``faces`` with the few input vertices that the check found out of bound put back,
    so that each lies on the surface again (0 mm): it splits the output triangle nearest
    to it into three that meet at it, or, where its foot on that triangle's plane falls
    beside one of its edges, that edge (its two triangles into four). None where that
    does not apply: more than :data:`_PUT_BACK` such vertices, an output edge or triangle
    out of bound, a foot near a corner, an edge not between exactly two triangles that
    run along it both ways, or a split that would turn a triangle over. The caller checks
    the result again: a split moves the surface nearby.

    On CThead bone, a schroeder run out of bound at 0.0001-0.001 of the diagonal had 1-10
    such vertices, 5-19 % over, and its edges and triangles within: a run again with those
    regions locked cost as much as the first. A quadric run across a job's blocks (512 x
    512 x 600) had one, its foot beside an edge: put back, schroeder's run (1 s) is saved."""
    import numpy as np

    from miss.measure import nearest_face

    stray = np.flatnonzero(np.nan_to_num(check.to_output) > limit_mm)
    if (
        len(stray) == 0
        or len(stray) > _PUT_BACK
        or (check.edge_mm > limit_mm).any()
        or (check.face_mm > limit_mm).any()
    ):
        return None
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    out = np.ascontiguousarray(faces, dtype=np.int32)
    for u in stray.tolist():  # Python ints, as the triangles hold
        f = nearest_face(verts[u], verts, out)
        a, b, c = (int(i) for i in out[f])
        normal = np.cross(verts[b] - verts[a], verts[c] - verts[a])
        area2 = float(normal @ normal)
        if area2 == 0.0:
            return None
        # barycentric coordinates of u's foot on the triangle's plane: each sub-triangle's
        # signed area over the whole's
        parts = [
            float(np.cross(verts[q] - verts[u], verts[r] - verts[u]) @ normal) / area2
            for q, r in ((b, c), (c, a), (a, b))
        ]
        split: list[tuple[int | None, tuple[int, int, int]]]
        if min(parts) > _PUT_BACK_MARGIN:
            split = [(f, (a, b, u)), (None, (b, c, u)), (None, (c, a, u))]
        elif (edge := _edge_split(verts, out, f, u, parts)) is not None:
            split = edge
        else:
            return None
        added = [tri for row, tri in split if row is None]
        out = np.concatenate([out, np.asarray(added, dtype=np.int32).reshape(-1, 3)])
        for row, tri in split:
            if row is not None:
                out[row] = tri
    return out


def _edge_split(
    verts: np.ndarray, out: np.ndarray, f: int, u: int, parts: list[float]
) -> list[tuple[int | None, tuple[int, int, int]]] | None:
    """Output triangle ``f`` and its neighbour across the edge beside which ``u``'s foot
    falls (``parts``: the foot's barycentric coordinates in ``f``), each split in two at
    ``u``: the rows they replace (None: a new row) and their corners, or None (see
    :func:`_put_back`)."""
    import numpy as np

    k = int(np.argmin(parts))
    if min(parts[(k + 1) % 3], parts[(k + 2) % 3]) <= _PUT_BACK_MARGIN:
        return None  # near a corner, not beside one edge
    r, p, q = (int(out[f, (k + i) % 3]) for i in range(3))  # f runs r -> p -> q
    both = np.flatnonzero((out == p).any(axis=1) & (out == q).any(axis=1))
    if len(both) != 2:
        return None
    g = int(both[both != f][0])
    corners = [int(i) for i in out[g]]
    at = corners.index(q)
    if corners[(at + 1) % 3] != p:
        return None  # the neighbour runs along the edge the same way: not oriented
    s = corners[(at + 2) % 3]  # g runs q -> p -> s
    split = [(f, (r, p, u)), (None, (r, u, q)), (g, (q, u, s)), (None, (u, p, s))]
    for parent, tris in (((r, p, q), split[:2]), ((q, p, s), split[2:])):
        before = np.cross(verts[parent[1]] - verts[parent[0]], verts[parent[2]] - verts[parent[0]])
        for _, (x, y, z) in tris:
            if float(np.cross(verts[y] - verts[x], verts[z] - verts[x]) @ before) <= 0.0:
                return None  # it would turn over
    return split


def _strays(mesh: Mesh, faces: np.ndarray, limit_mm: float) -> bool:
    """Whether some of ``_SCREEN`` of the input vertices the output ``faces`` dropped (evenly
    spread over them) lie farther than ``limit_mm`` from it: a run that far out is known out
    of bound without the whole check (a quadric run several times over the bound, as on
    CThead, strays at most of them)."""
    from miss.measure import distances_to, dropped_vertices
    from miss.types import Mesh

    _, dropped = dropped_vertices(mesh.faces, faces, mesh.n_vertices)
    if len(dropped) == 0:
        return False
    some = dropped[:: max(1, len(dropped) // _SCREEN)]
    after = Mesh(vertices=mesh.vertices, faces=faces)
    return bool((distances_to(mesh.vertices[some], after, limit_mm) > limit_mm).any())


def _out_of_bound(
    mesh: Mesh, check: BoundCheck, bound_mm: float, share: float = 1.0, rings: int = 2
) -> np.ndarray:
    """(N,) bool: input vertices near where the output strays past ``share`` of the bound
    (dropped vertices, the ends of stray edges, the corners of stray triangles), grown by
    ``rings`` rings of the input's triangles."""
    import numpy as np

    half = share * bound_mm
    bad = np.nan_to_num(check.to_output) > half
    bad[check.edges[check.edge_mm > half].ravel()] = True
    bad[check.faces[check.face_mm > half].ravel()] = True
    for _ in range(rings):
        touched = bad[mesh.faces].any(axis=1)
        bad[mesh.faces[touched].ravel()] = True
    return bad


def measured(
    report: DecimationReport,
    before: Mesh,
    after: Mesh,
    samples: int = SAMPLES,
    side: Future[Side] | RemoteSide | None = None,
) -> DecimationReport:
    """``report`` with the two-sided deviation of ``after`` from ``before`` measured (mm),
    from ``samples`` points on each surface; a report already measured is returned as is.

    A job measures after its files are written (the viewer draws the model meanwhile):
    ``decimate(..., measure=False)`` now, this later. ``side``: :func:`measuring_later`'s
    for ``before`` and ``samples``, started before the decimation; used if it is done (and
    did not fail), else the measurement makes that half itself (same figures either way);
    or a :class:`miss.measure.measurer.RemoteSide`: the measuring process measures (made here if
    it cannot).
    """
    if report.max_error_mm is not None:
        return report
    from miss.measure.measurer import MeasurerGone, RemoteSide

    start = time.perf_counter()
    figures = None
    if isinstance(side, RemoteSide):  # made in the measuring process: it measures there
        with contextlib.suppress(MeasurerGone):
            figures = side.deviation(after)
        side = None
    if figures is None:
        from miss.measure import deviation  # native, or numba's where it is loaded

        # a side that failed (e.g. out of memory on its thread) is made again here, as one
        # not done
        done = side is not None and side.done() and side.exception() is None
        ready = side.result() if side is not None and done else None
        dev = deviation(before, after, samples=samples, side=ready)
        figures = dev.max_mm, dev.mean_mm
    return replace(
        report,
        max_error_mm=figures[0],
        mean_error_mm=figures[1],
        measure_seconds=time.perf_counter() - start,
    )
