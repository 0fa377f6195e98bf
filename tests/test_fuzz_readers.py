"""Mutation fuzzing of the readers with hypothesis: damaged DICOM, NIfTI, NRRD, MetaImage
and zip inputs load as a sound ``Volume`` or are refused with a ``MissError`` - never any
other exception (warnings count: the test suite turns them into errors, and on the
command line they would be stray lines on stderr).

Reproducible: ``derandomize=True`` draws the same examples on every run, and no example
database is written. A longer, seeded run: ``python tests/corpus/fuzz.py SECONDS SEED``.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from corpus.fuzz import CORE, KINDS, apply, fuzz_readers, outcome, seeds, write_case
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

OPS = st.lists(
    st.tuples(st.sampled_from(KINDS), st.integers(0, 1 << 16), st.integers(0, 1 << 16)),
    min_size=1,
    max_size=4,
)
FUZZ = settings(
    max_examples=150,
    derandomize=True,
    database=None,
    deadline=None,  # hangs are caught by the test's timeout, not by a timing assertion
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


@pytest.mark.timeout(300)
@pytest.mark.parametrize("fmt", CORE)
def test_mutated_input_loads_soundly_or_is_refused(fmt: str, tmp_path: Path) -> None:
    @FUZZ
    @given(ops=OPS)
    def check(ops: list[tuple[str, int, int]]) -> None:
        result, detail = outcome(write_case(tmp_path, fmt, ops))
        assert result in ("loaded", "refused"), f"{fmt} {ops}: {result}: {detail}"

    check()


def test_mutations_change_the_input() -> None:
    """The fuzzer's own sanity: each kind of mutation really alters a seed."""
    data = seeds()["nrrd"]
    for kind in KINDS:
        assert apply(data, [(kind, 40, 7)]) != data, kind


@pytest.mark.slow
def test_fuzz_loop_counts_every_case() -> None:
    """The bounded loop the robustness benchmark runs (a short run here)."""
    report = fuzz_readers(seconds=3.0, seed=1)
    assert report["cases"] > 0
    assert report["cases"] == report["loaded"] + report["refused"] + sum(report["crashes"].values())
    assert report["crashes"] == {}, report["examples"]
