"""The ``miss`` command line: info, convert, ingest, demo, serve, user, audit, backup, restore.

Bad input ends with one line on stderr naming the problem and the fix, exit code 2.
``convert``'s job options are generated from the job's declaration (:mod:`miss.spec`).
"""

from __future__ import annotations

import argparse
import difflib
import importlib
import os
import re
import sys
from collections.abc import Sequence
from typing import NoReturn

EXIT_BAD_INPUT = 2
# What argparse takes for a negative number rather than an option (``--level -500``).
_NUMBER = re.compile(r"^-\d+$|^-\d*\.\d+$")

#: Each command: its one-line help, and the module with its ``arguments`` (adds them to
#: its parser) and ``run`` (does it) functions. A command's module loads only when that
#: command runs (``convert``'s options load the job's declaration): ``miss --help`` and
#: ``miss info`` start without the others.
COMMANDS: dict[str, tuple[str, str, str, str]] = {
    "info": (
        "describe a volume (DICOM folder/zip, NIfTI, NRRD, MetaImage)",
        "miss.cli.info", "add_arguments", "cmd_info",
    ),
    "convert": ("volume -> surface model(s)", "miss.cli.convert", "add_arguments", "cmd_convert"),
    "ingest": (
        "store a volume in the server's data folder (big NIfTI files read slice by slice)",
        "miss.cli.ingest", "add_arguments", "cmd_ingest",
    ),
    "demo": (
        "write the synthetic CT head phantom as NIfTI",
        "miss.cli.demo", "add_arguments", "cmd_demo",
    ),
    "serve": ("start the web system", "miss.cli.admin", "serve_arguments", "cmd_serve"),
    "user": ("manage the web system's accounts", "miss.cli.admin", "user_arguments", "cmd_user"),
    "backup": (
        "copy the database and the data folder, also while the server runs",
        "miss.cli.admin", "backup_arguments", "cmd_backup",
    ),
    "restore": (
        "make an empty data folder from a backup",
        "miss.cli.admin", "restore_arguments", "cmd_restore",
    ),
    "audit": (
        "print the web system's audit log", "miss.cli.admin", "audit_arguments", "cmd_audit",
    ),
    "pacs": (
        "search the PACS, fetch a series, send a model back",
        "miss.cli.pacs", "add_arguments", "cmd_pacs",
    ),
}  # fmt: skip


class _Lenient(Exception):
    """A usage error met while re-reading leniently (:meth:`_Parser._left_over`)."""


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error on one line, an unknown option before anything
    else (argparse would first complain of a missing argument, or leave the option to the
    top-level parser, whose hint names ``miss --help`` rather than the command's)."""

    _lenient = False  # class-wide: nested parsers re-read leniently with their parent
    _words: list[str] = []

    def parse_known_args(  # type: ignore[override]
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        self._words = list(sys.argv[1:] if args is None else args)
        # argparse's own default, made here so that the typed answer is a Namespace
        fresh = argparse.Namespace() if namespace is None else namespace
        parsed, extras = super().parse_known_args(self._words, fresh)
        if extras and not _Parser._lenient:
            # Said by the parser that met them, so the hint names the command typed.
            self.error(self._unknown(extras) or f"unrecognized arguments: {' '.join(extras)}")
        return parsed, extras

    def error(self, message: str) -> NoReturn:
        if _Parser._lenient:
            raise _Lenient(message)
        message = self._unknown(self._left_over()) or message
        # prog is the command as typed so far: "miss", "miss convert", "miss user add"
        self.exit(EXIT_BAD_INPUT, f"miss: {message} (see '{self.prog} --help')\n")

    def _left_over(self) -> list[str]:
        """The words this parser leaves over when nothing is required; [] if they hold
        another usage error."""
        required = [action for action in self._actions if action.required]
        _Parser._lenient = True
        try:
            for action in required:
                action.required = False
            return super().parse_known_args(self._words)[1]
        except _Lenient:
            return []
        finally:
            _Parser._lenient = False
            for action in required:
                action.required = True

    def _unknown(self, words: list[str]) -> str | None:
        """``"unknown option --x"`` for the first option-like word, with the nearest known one."""
        for word in words:
            if word == "--":
                break
            if word.startswith("-") and len(word) > 1 and not _NUMBER.match(word):
                name = word.split("=", 1)[0]
                known = [o for action in self._actions for o in action.option_strings]
                near = difflib.get_close_matches(name, known, n=1)
                return f"unknown option {name}" + (f" (did you mean {near[0]}?)" if near else "")
        return None


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The ``miss`` parser; ``only``: the one command given its arguments (the others are
    listed with their help and parse nothing), None: every command."""
    parser = _Parser(prog="miss", description="MISS - CT/MRI volumes to shared 3-D surface models.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    for name, (text, module, arguments, _) in COMMANDS.items():
        command = sub.add_parser(name, help=text, description=text)
        if only is None or name == only:
            getattr(importlib.import_module(module), arguments)(command)
    return parser


def _command_in(argv: Sequence[str]) -> str:
    """The command ``argv`` names ("" if none): the top level takes no option but ``-h``."""
    return next((word for word in argv if not word.startswith("-")), "")


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``miss`` command line with ``argv`` (default ``sys.argv[1:]``); the exit status."""
    from miss._process import LEAN_ENV, as_command
    from miss.errors import MissError

    argv = sys.argv[1:] if argv is None else list(argv)
    if as_command():  # not when a program calls main(): the processes it starts are lean too
        os.environ.setdefault(LEAN_ENV, "1")
    # On a terminal whose locale cannot spell "mm³" (ASCII, no UTF-8 coercion) a character
    # it lacks is written escaped, not a crash of the whole command (stderr already does).
    if hasattr(sys.stdout, "reconfigure"):
        sys.stdout.reconfigure(errors="backslashreplace")
    args = build_parser(_command_in(argv)).parse_args(argv)
    _, module, _, run = COMMANDS[args.command]
    try:
        return getattr(importlib.import_module(module), run)(args)
    except MissError as exc:
        print(f"miss: {exc}", file=sys.stderr)
    except MemoryError:
        print(
            "miss: out of memory; use a larger --sample-rate or a smaller slice range",
            file=sys.stderr,
        )
    except OSError as exc:
        print(
            f"miss: {exc.filename or ''}: {exc.strerror or exc}; check the path and permissions",
            file=sys.stderr,
        )
    except KeyboardInterrupt:
        print("miss: interrupted", file=sys.stderr)
    return EXIT_BAD_INPUT
