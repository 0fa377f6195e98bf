"""The job is declared once (miss.spec): the REST body and the CLI options are generated
from it, so every field is reachable from both, with one name, one default, one meaning."""

from __future__ import annotations

import inspect
import io
from dataclasses import fields
from typing import Any

import pytest
import trimesh

from miss import BadParameter
from miss.cli import build_parser
from miss.cli.options import flags, job_form
from miss.demo import phantom
from miss.export import WRITERS
from miss.pipeline import run
from miss.server.core.schemas import ModelRequest, PartRequest
from miss.smooth import smooth_mesh, windowed_sinc
from miss.spec import (
    FORMATS,
    Decimation,
    JobSpec,
    Region,
    Structure,
    default_of,
    form_fields,
    form_name,
)
from miss.structures.labelmap import label_surfaces
from miss.surface import extract_surface

#: A value unlike the default for every field of the form: (CLI words, JSON value).
EXAMPLES: dict[str, tuple[list[str], Any]] = {
    "sample_rate": (["--sample-rate", "2,2,3"], [2, 2, 3]),
    "start_slice": (["--start-slice", "3"], 3),
    "end_slice": (["--end-slice", "40"], 40),
    "roi": (["--roi", "1,50,2,60,3,40"], [1, 50, 2, 60, 3, 40]),
    "level": (["--level", "250.5"], 250.5),
    "levels": (["--level", "-500", "--level", "300"], [-500.0, 300.0]),
    "labels": (["--labels", "4,1"], [1, 4]),
    "components": (["--components", "split"], "split"),
    "min_size_mm3": (["--min-size-mm3", "12.5"], 12.5),
    "max_parts": (["--max-parts", "7"], 7),
    "smooth": (["--smooth", "15"], 15),
    "passband": (["--passband", "0.05"], 0.05),
    "parts": (
        ["--part", "level=300,name=bone,color=#f1d691,opacity=0.5", "--part", "level=-500"],
        [{"level": 300, "name": "bone", "color": "#f1d691", "opacity": 0.5}, {"level": -500}],
    ),
    "decimate": (["--decimate", "schroeder"], "schroeder"),
    "error_bound": (["--error-bound", "0.0005"], 0.0005),
    "reduce": (["--reduce", "0.5"], 0.5),
    "max_error": (["--max-error", "0.02"], 0.02),
    "schedule": (["--schedule", "paper"], "paper"),
}
#: Fields a person does not type: the server writes every format, the CLI the -o ones.
NOT_TYPED = {"formats"}
#: What every example needs beside it (a structure), unless it is one itself.
BASE = {"level": 100.0}
STRUCTURE_FIELDS = {"level", "levels", "labels", "parts"}


def _cli_spec(words: list[str]) -> JobSpec:
    args = build_parser().parse_args(["convert", "in.nii", "-o", "out.glb", *words])
    return JobSpec.from_dict({**job_form(args), "formats": ["glb"]})


def _api_spec(body: dict[str, Any]) -> JobSpec:
    return ModelRequest(volume="v", **body).spec().with_formats(["glb"])


def test_every_field_has_an_example_or_a_reason() -> None:
    names = {form_name(f) for _, _, f in form_fields()}
    assert names == set(EXAMPLES) | NOT_TYPED


def test_the_rest_body_is_the_form() -> None:
    api = set(ModelRequest.model_fields) - {"volume"}
    assert api == set(EXAMPLES)
    for _, _, f in form_fields():
        name = form_name(f)
        if name in api:
            assert ModelRequest.model_fields[name].default == default_of(f), name
            assert ModelRequest.model_fields[name].description == f.metadata["help"], name
    assert set(PartRequest.model_fields) == {f.name for f in fields(Structure)}


def test_every_typed_field_is_a_cli_option() -> None:
    convert = build_parser()._subparsers._group_actions[0].choices["convert"]  # type: ignore[union-attr]
    options = {s for action in convert._actions for s in action.option_strings}
    for _, _, f in form_fields():
        if f.metadata.get("cli") is False:
            continue
        assert set(flags(f)) <= options, form_name(f)


def test_cli_defaults_are_the_spec_defaults() -> None:
    """Nothing typed: the CLI and the API make the same job, the spec's defaults."""
    assert _cli_spec(["--level", "100"]) == _api_spec(BASE) == JobSpec.of(**BASE)


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_a_field_means_the_same_from_both(name: str) -> None:
    words, value = EXAMPLES[name]
    base = {} if name in STRUCTURE_FIELDS else BASE
    base_words = [] if name in STRUCTURE_FIELDS else ["--level", "100"]
    if name == "labels":  # labels alone: the level of the base is kept too
        base, base_words = BASE, ["--level", "100"]
    from_cli = _cli_spec([*base_words, *words])
    from_api = _api_spec({**base, name: value})
    assert from_cli == from_api
    assert from_cli != JobSpec.of(**BASE)  # the example really changed something
    assert from_cli.key() == from_api.key()


def test_formats_are_the_writers() -> None:
    assert tuple(WRITERS) == FORMATS


@pytest.mark.parametrize(
    ("form", "message"),
    [
        ({"level": 300, "parts": [{"level": 100}]}, "not both"),
        ({"parts": [{"level": 300, "labels": "all"}]}, "not both"),
        ({"parts": [{"level": 300, "colour": "red"}]}, "unknown part field"),
        ({"parts": [{"level": 300, "color": "red"}]}, "#rrggbb"),
        ({"parts": [{"level": 300, "opacity": 0}]}, "opacity must be in"),
        ({"parts": "level=300"}, "list of objects"),
        (
            {"labels": "all", "parts": [{"labels": [1], "name": "x", "smooth": 3}]},
            "same components",
        ),
        ({"parts": [{"labels": "all", "name": "organs"}]}, "goes with one label"),
        ({"levels": list(range(17))}, "at most 16"),
        ({"level": 300, "roi": [1, 2, 3]}, "six voxel indices"),
        ({"level": 300, "max_parts": 0}, "max_parts"),
    ],
)
def test_bad_forms_say_what_to_do(form: dict[str, Any], message: str) -> None:
    with pytest.raises(BadParameter, match=message):
        JobSpec.from_dict(form)


def test_a_part_s_name_colour_and_opacity_reach_the_file() -> None:
    """Styles are the server's business now: written into the model, not kept in a browser."""
    spec = JobSpec.of(
        parts=[
            {"level": -500, "name": "Haut", "color": "#336699", "opacity": 0.4},
            {"level": 300, "name": "Knochen"},
        ],
        sample_rate=2,
        formats=("glb", "stl"),
    )
    result = run(phantom(64, 3.0), spec)
    parts = result.stats()["parts"]
    assert [p["name"] for p in parts] == ["Haut", "Knochen"]
    assert parts[0]["color"] == pytest.approx([0x33 / 255, 0x66 / 255, 0x99 / 255], abs=1e-4)
    assert parts[0]["opacity"] == 0.4 and parts[1]["opacity"] == 1.0
    loaded = trimesh.load(io.BytesIO(result.artifacts["glb"]), file_type="glb")
    assert set(loaded.geometry) == {"Haut", "Knochen"}
    stl = result.artifacts["stl"]  # two parts: one solid of both (it was a zip)
    assert stl[:2] != b"PK" and len(stl) == 84 + 50 * result.scene.n_triangles


def test_one_part_in_a_one_mesh_format_is_the_plain_file() -> None:
    result = run(phantom(64, 3.0), JobSpec.of(level=300.0, formats=("stl", "glb")))
    data = result.artifacts["stl"]
    assert data[:2] != b"PK" and len(data) == 84 + 50 * result.scene.n_triangles
    assert [p["name"] for p in result.stats()["parts"]] == ["bone (300 HU)"]


def _key_before_the_spec(stored: dict[str, Any]) -> str:
    """How JobSpec.key() hashed a stored row's parameters before this module existed."""
    import hashlib
    import json

    defaults = {"levels": None, "labels": None, "components": "all", "min_size_mm3": 0.0,
                "smooth": None, "passband": 0.1}  # fmt: skip
    d = {k: v for k, v in stored.items() if k != "formats"}
    sr = d["sample_rate"]
    d["sample_rate"] = [sr] * 3 if isinstance(sr, int) else list(sr)
    for name, default in defaults.items():
        if d[name] == default:
            del d[name]
    return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:32]


@pytest.mark.parametrize(
    "changes",
    [
        {"level": 300.0, "sample_rate": 2},
        {"levels": [-500.0, 300.0], "components": "split", "min_size_mm3": 50.0},
        {"labels": [1, 4], "smooth": 10},
        {"level": 300.0, "levels": [100.0, 300.0]},  # both given: both kept in the key
        {"level": 250.0, "start_slice": 3, "end_slice": 40, "decimate": "schroeder"},
    ],
)
def test_rows_stored_before_the_spec_keep_their_keys(changes: dict[str, Any]) -> None:
    """A model row keeps its spec as the form; the worker reads it back and the same
    parameters find it again, so no stored model is computed twice (nothing to migrate)."""
    stored = {"level": None, "sample_rate": 1, "start_slice": None, "end_slice": None,
              "roi": None, "decimate": "quadric", "error_bound": 0.0002, "reduce": 0.9,
              "max_error": 0.01, "formats": list(FORMATS), "levels": None, "labels": None,
              "components": "all", "min_size_mm3": 0.0, "smooth": None, "passband": 0.1,
              **changes}  # fmt: skip
    # models made before bounds were held used the paper's schedule: "schedule": "paper"
    # finds them; a body without it asks for a guaranteed bound, a new model
    paper = {**stored, "schedule": "paper"}
    assert JobSpec.from_dict(paper).key() == _key_before_the_spec(stored)
    assert JobSpec.from_dict(stored).key() != _key_before_the_spec(stored)
    # and so does a body that says so, with the bound the old default had (0.0002)
    body = {**changes, "schedule": "paper", "error_bound": 0.0002}
    assert _api_spec(body).key() == _key_before_the_spec(stored)


def _defaults(function: Any) -> dict[str, Any]:
    return {
        name: p.default
        for name, p in inspect.signature(function).parameters.items()
        if p.default is not inspect.Parameter.empty
    }


def _spec_defaults(cls: type) -> dict[str, Any]:
    return {f.name: default_of(f) for f in fields(cls)}


def test_the_python_api_defaults_are_the_specs() -> None:
    """miss.decimate, extract_surface, the label-map path and the smoothing take their
    defaults from the job's declaration: the same as the REST body's and the CLI's."""
    import miss

    decimation = _spec_defaults(Decimation)
    assert {k: _defaults(miss.decimate)[k] for k in decimation} == decimation
    labelled = _defaults(label_surfaces)
    assert {k: labelled[k] for k in ("method", "reduce", "error_bound", "max_error")} == {
        k: decimation[k] for k in ("method", "reduce", "error_bound", "max_error")
    }
    passband = default_of(Structure.__dataclass_fields__["passband"])
    assert labelled["passband"] == passband
    assert _defaults(windowed_sinc)["passband"] == _defaults(smooth_mesh)["passband"] == passband
    region = _spec_defaults(Region)
    surface = _defaults(miss.extract_surface)
    assert surface["sample_rate"] == region["sample_rate"]
    assert surface["roi"] == region["roi"] and surface["slices"] is None
    assert region["start_slice"] is region["end_slice"] is None
    # and today's values (behaviour unchanged)
    assert decimation == {
        "method": "quadric",
        "error_bound": 0.002,
        "reduce": 0.9,
        "max_error": 0.01,
        "schedule": "guaranteed",
    }
    assert (passband, region["sample_rate"]) == (0.1, 1)
    assert extract_surface is miss.extract_surface
