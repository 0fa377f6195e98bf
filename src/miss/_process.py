"""Facts about this process: the cores it may use, and whether it is the ``miss`` command
(or a process MISS started), which loads what it needs on first use."""

from __future__ import annotations

import os
import sys

#: Set by the ``miss`` command for itself and the processes it starts.
LEAN_ENV = "MISS_LEAN_IMPORT"


def as_command() -> bool:
    """Whether this process is the ``miss`` command (its script, ``python -m miss`` or
    ``-m miss.cli``), another of MISS's modules run as a program, or a process that MISS
    started (``MISS_LEAN_IMPORT=1``: job workers, measurers; the confined reader loads
    no ``miss`` package at all)."""
    if os.environ.get(LEAN_ENV) == "1" or os.path.basename((sys.argv or [""])[0]) == "miss":
        return True
    argv = list(getattr(sys, "orig_argv", ()))  # the interpreter's own -m comes first
    at = argv.index("-m") if "-m" in argv else -1
    module = argv[at + 1] if 0 <= at < len(argv) - 1 else ""
    return module == "miss" or module.startswith("miss.")


def usable_cores() -> int:
    """The cores this process may run on (its affinity; what numba's threads default to),
    at least one."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
