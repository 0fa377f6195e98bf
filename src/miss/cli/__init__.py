"""The ``miss`` command line: info, convert, ingest, demo, serve, user, audit, backup, restore.

Bad input ends with one line on stderr naming the problem and the fix, exit code 2.
``convert``'s job options are generated from the job's declaration (:mod:`miss.spec`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Sequence
from typing import NoReturn

from miss.cli import admin, convert, demo, info, ingest, pacs

EXIT_BAD_INPUT = 2


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error on one line."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_BAD_INPUT, f"miss: {message} (see 'miss {self.prog.split()[-1]} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="miss", description="MISS - CT/MRI volumes to shared 3-D surface models.")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    info.add_parser(sub)
    convert.add_parser(sub)
    ingest.add_parser(sub)
    demo.add_parser(sub)
    admin.add_serve_parser(sub)
    admin.add_parsers(sub)
    pacs.add_parser(sub)
    return parser


COMMANDS: dict[str, Callable[[argparse.Namespace], int]] = {
    "info": info.cmd_info,
    "convert": convert.cmd_convert,
    "ingest": ingest.cmd_ingest,
    "demo": demo.cmd_demo,
    "serve": admin.cmd_serve,
    "user": admin.cmd_user,
    "audit": admin.cmd_audit,
    "backup": admin.cmd_backup,
    "restore": admin.cmd_restore,
    "pacs": pacs.cmd_pacs,
}


def main(argv: Sequence[str] | None = None) -> int:
    from miss.errors import MissError

    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args)
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
