"""The cores this process may run on, for the native kernels and thread pools that size
themselves by it."""

from __future__ import annotations

import os


def usable_cores() -> int:
    """The cores this process may run on (its affinity; what numba's threads default to),
    at least one."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return os.cpu_count() or 1
