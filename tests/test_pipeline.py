"""The job as data: validation, caching key, and a full run on the demo phantom."""

from __future__ import annotations

import sys
from concurrent.futures import Future
from dataclasses import replace

import pytest

from miss import BadParameter
from miss.demo import phantom
from miss.measure import measurer
from miss.measure.measurer import RemoteSide
from miss.pipeline import run
from miss.spec import JobSpec
from miss.structures import build
from miss.structures.build import build_scene


def test_run_produces_every_requested_format() -> None:
    spec = JobSpec.of(level=300.0, sample_rate=2, formats=("glb", "wrl", "stl"))
    stages: list[str] = []
    result = run(phantom(), spec, progress=lambda stage, f: stages.append(stage))
    assert set(result.artifacts) == {"glb", "wrl", "stl"}
    assert result.artifacts["wrl"].startswith(b"#VRML V2.0 utf8")
    assert stages[0] == "surface" and stages[-1] == "done"
    stats = result.stats()
    assert stats["triangles"] == result.mesh.n_triangles > 1000
    # the default: the bound is a cap, measured to hold; decimation stops at it
    decimation = stats["decimation"]
    assert decimation["schedule"] == "guaranteed" and decimation["bound_held"]
    assert 0 < decimation["max_error_mm"] <= decimation["bound_mm"]
    assert decimation["stopped_by"] == "bound" and decimation["achieved_reduction"] > 0
    # quadric was asked for (the default); the held model is schroeder's, and says so
    assert decimation["method"] == "quadric" and decimation["finished_with"] == "schroeder"
    # its check is the measurement, timed as one (not inside "decimate", not a 0 s stage)
    checked = result.report.measure_seconds
    assert checked > 0 and checked <= result.seconds["measure"] <= checked + 0.05


def test_the_papers_schedule_meets_reduce_within_the_bound_it_ended_at() -> None:
    spec = JobSpec.of(level=300.0, sample_rate=2, formats=("glb",), schedule="paper")
    decimation = run(phantom(), spec).stats()["decimation"]
    assert decimation["achieved_reduction"] >= 0.85 and decimation["stopped_by"] == "reduce"
    assert 0 < decimation["max_error_mm"] <= decimation["bound_mm"]


def test_a_job_measured_after_starts_the_measurement_while_it_decimates(monkeypatch) -> None:
    import numba  # noqa: F401  (loaded, as in a server's warmed-up worker)

    spec = JobSpec.of(level=300.0, sample_rate=2, formats=("glb",), schedule="paper")
    built = build_scene(phantom(), spec, measure=False, measure_later=True)
    (source,) = built.sources
    assert source.side is not None  # the undecimated surface's half, started before decimating
    source.side.result()
    ahead = built.measured()
    # the same build measured with nothing made ahead: the same figures, to the bit
    alone = replace(built, sources=(replace(source, side=None),)).measured()
    assert ahead.reports == tuple(
        replace(r, measure_seconds=a.measure_seconds)
        for r, a in zip(alone.reports, ahead.reports, strict=True)
    )
    assert ahead.reports[0].max_error_mm > 0
    # a side whose thread failed (or has not finished) is made again by the measurement
    failed: Future = Future()
    failed.set_exception(MemoryError("no room on the side thread"))
    pending: Future = Future()
    for side in (failed, pending):
        again = replace(built, sources=(replace(source, side=side),)).measured()
        assert again.reports[0].max_error_mm == alone.reports[0].max_error_mm
        assert again.reports[0].mean_error_mm == alone.reports[0].mean_error_mm
    # in a process without numba yet (a fresh `miss convert --measure`) the native kernels
    # make it on the thread; where they were not built, it goes to the measuring process
    # (miss.measure.measurer), which measures it: the same figures either way
    with monkeypatch.context() as m:
        m.delitem(sys.modules, "numba")
        native = build_scene(phantom(), spec, measure=False, measure_later=True)
        assert isinstance(native.sources[0].side, Future)  # a thread, not a process
        here = native.measured().reports[0]
        m.setattr(build, "native", lambda: False)
        m.setattr(measurer, "native", lambda: False)
        fresh = build_scene(phantom(), spec, measure=False, measure_later=True)
    assert isinstance(fresh.sources[0].side, RemoteSide)
    there = fresh.measured().reports[0]
    for got in (here, there):
        assert (got.max_error_mm, got.mean_error_mm) == (
            alone.reports[0].max_error_mm,
            alone.reports[0].mean_error_mm,
        )
    # nothing is started for a build that is not measured after, nor for a guaranteed bound
    assert build_scene(phantom(), spec, measure=False).sources[0].side is None
    guaranteed = JobSpec.of(level=300.0, sample_rate=2, formats=("glb",))
    assert (
        build_scene(phantom(), guaranteed, measure=False, measure_later=True).sources[0].side
        is None
    )


def test_a_build_starts_its_first_parts_measurements_only(monkeypatch) -> None:
    import numba  # noqa: F401

    # a split surface may have 100 parts: only the first SIDES_AHEAD are started ahead
    monkeypatch.setattr(build, "SIDES_AHEAD", 1)
    spec = JobSpec.of(
        level=300.0, sample_rate=2, formats=("glb",), schedule="paper", components="split"
    )
    built = build_scene(phantom(), spec, measure=False, measure_later=True)
    assert [s.side is not None for s in built.sources] == [True, False]
    ahead = built.measured()
    alone = replace(built, sources=tuple(replace(s, side=None) for s in built.sources))
    assert [r.max_error_mm for r in ahead.reports] == [
        r.max_error_mm for r in alone.measured().reports
    ]


def test_key_ignores_formats_and_normalises_sample_rate() -> None:
    a = JobSpec.of(level=300.0, sample_rate=2, formats=("glb",))
    b = JobSpec.from_dict({"level": 300.0, "sample_rate": [2, 2, 2], "formats": ["wrl"]})
    assert a.key() == b.key()
    assert a.key() != JobSpec.of(level=301.0, sample_rate=2).key()


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({}, "needs a 'level'"),
        ({"level": "bone"}, "level must be a number"),
        ({"level": 1, "sample_rate": 0}, "sample_rate must be an integer >= 1"),
        ({"level": 1, "sample_rate": [1, 2]}, "sample_rate must be"),
        ({"level": 1, "reduce": 1.5}, r"reduce must be in \[0, 1\)"),
        ({"level": 1, "start_slice": 9, "end_slice": 3}, "swap them"),
        ({"level": 1, "decimate": "fast"}, "decimate must be one of"),
        ({"level": 1, "formats": ["dxf"]}, "unknown output format"),
        ({"level": 1, "colour": "red"}, "unknown job parameter"),
    ],
)
def test_from_dict_rejects_bad_input_with_a_clear_message(data: dict, message: str) -> None:
    with pytest.raises(BadParameter, match=message):
        JobSpec.from_dict(data)


def test_export_options_reach_the_writer() -> None:
    """The server asks for meshopt-compressed glTF: far smaller, same triangles."""
    spec = JobSpec.of(level=300.0, sample_rate=2, formats=("glb",))
    plain = run(phantom(), spec).artifacts["glb"]
    packed = run(phantom(), spec, export_options={"glb": {"compress": True}}).artifacts["glb"]
    assert b"EXT_meshopt_compression" in packed and b"EXT_meshopt_compression" not in plain
    assert len(packed) < 0.5 * len(plain)
