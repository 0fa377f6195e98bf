"""``miss convert``'s job options, generated from the job's declaration.

Every field of :mod:`miss.spec` becomes one option with the field's help text, its
spelling from ``metadata`` and no argparse default: a value left out is not in the
form, so the spec's own default applies, the same one the REST API applies.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from dataclasses import MISSING, Field, fields
from pathlib import Path
from typing import Any

from miss.errors import UnreadableVolume
from miss.spec import FileSource, Source, Structure, default_of, form_fields, form_name


def whole_numbers(text: str) -> int | tuple[int, ...]:
    """``N`` or ``X,Y,Z`` (or any count, the spec checks how many)."""
    try:
        values = tuple(int(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected whole numbers separated by commas, got {text!r}"
        ) from None
    return values[0] if len(values) == 1 else values


def _part(text: str) -> dict[str, Any]:
    """``level=300,name=bone,color=#f1d691``: one part, its values typed as its fields."""
    declared = {f.name: f for f in fields(Structure)}
    entry: dict[str, Any] = {}
    for item in text.split(","):
        key, sep, value = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in declared:
            raise argparse.ArgumentTypeError(
                f"a part is key=value pairs such as level=300,name=bone; {item!r} is not "
                f"(keys: {', '.join(declared)})"
            )
        entry[key] = TEXT[declared[key].metadata.get("text", "str")](value.strip())
    return entry


def _number(kind: Callable[[str], Any]) -> Callable[[str], Any]:
    def parse(text: str) -> Any:
        try:
            return kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None

    parse.__name__ = kind.__name__
    return parse


#: How the command line reads each kind of value (a field's ``metadata["text"]``).
TEXT: dict[str, Callable[[str], Any]] = {
    "str": str,
    "int": _number(int),
    "float": _number(float),
    "ints": whole_numbers,
    "part": _part,
}


def flags(f: Field[Any]) -> tuple[str, ...]:
    """The option strings of a field: its declared ``flag`` or ``--form-name``."""
    return f.metadata.get("flag", ("--" + form_name(f).replace("_", "-"),))


def _help(f: Field[Any]) -> str:
    default = default_of(f)
    if default is None or f.metadata.get("repeat") or f.default is MISSING:
        return f.metadata["help"]
    return f"{f.metadata['help']} (default {default})"


def _add(group: Any, f: Field[Any], dest: str) -> None:
    meta = f.metadata
    kwargs: dict[str, Any] = {"dest": dest, "default": None, "help": _help(f)}
    if "choices" in meta:
        kwargs["choices"] = meta["choices"]
    else:
        kwargs["type"] = TEXT[meta.get("text", "str")]
    if "metavar" in meta:
        kwargs["metavar"] = meta["metavar"]
    if meta.get("repeat"):
        kwargs["action"] = "append"
    group.add_argument(*flags(f), **kwargs)


def add_source_options(parser: argparse.ArgumentParser, *only: str) -> None:
    """PATH and the options of :class:`~miss.spec.FileSource` (or ``only`` these)."""
    for f in fields(FileSource):
        if only and f.name not in only:
            continue
        if f.name == "path":
            parser.add_argument("path", help=f.metadata["help"])
        else:
            _add(parser, f, f.name)


def add_job_options(parser: argparse.ArgumentParser) -> None:
    """One option per field of the job form, grouped as the spec groups them."""
    groups: dict[str, Any] = {}
    for attr, cls, f in form_fields():
        if f.metadata.get("cli") is False:
            continue
        if attr not in groups:
            about = (cls.__doc__ or "").split("\n")[0].replace("``", "")
            groups[attr] = parser.add_argument_group(attr, about)
        _add(groups[attr], f, form_name(f))


def job_form(args: argparse.Namespace) -> dict[str, Any]:
    """The form the options given spell (options left out are not in it). ``--level``
    given once is ``level``; repeated, ``levels``."""
    form: dict[str, Any] = {}
    for _, _, f in form_fields():
        if f.metadata.get("cli") is False:
            continue
        value = getattr(args, form_name(f))
        if value is None:
            continue
        if f.metadata.get("repeat") == "levels" and len(value) > 1:
            form["levels"] = value
        elif f.metadata.get("repeat") == "levels":
            form["level"] = value[0]
        else:
            form[form_name(f)] = value
    return form


def source_of(args: argparse.Namespace) -> Source:
    """PATH as a source: ``dicomweb:STUDY/SERIES`` a series on the PACS, else a file."""
    if str(args.path).startswith("dicomweb:"):
        from miss.pacs.source import PacsSeries, parse, pick_server

        found = parse(args.path)
        assert found is not None  # the prefix is there
        study, series = found
        return PacsSeries(pick_server(), study, series)
    given = {f.name: getattr(args, f.name) for f in fields(FileSource)}
    for name in ("path", "label_map"):  # said at once, before the job's libraries load
        if given.get(name) and not Path(given[name]).exists():
            raise UnreadableVolume(f"{Path(given[name])}: no such file or folder; check the path.")
    return FileSource(**{k: v for k, v in given.items() if v is not None})
