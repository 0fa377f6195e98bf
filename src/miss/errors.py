"""MISS exceptions: each message names the problem and the fix.

The CLI prints ``str(exc)`` on one line and exits with code 2; the server answers
4xx with the message as ``detail``.
"""

from __future__ import annotations


class MissError(Exception):
    """Base class for every error MISS raises on purpose (bad input, bad parameter)."""


class UnreadableVolume(MissError, ValueError):
    """A file or folder that cannot be read as a volume (missing, truncated, wrong magic)."""


class UnsupportedFormat(MissError, ValueError):
    """A file extension or format MISS has no reader or writer for."""


class BadParameter(MissError, ValueError):
    """A processing parameter out of range (sample rate, slices, reduce, level ...)."""


class EmptySurface(MissError, ValueError):
    """The chosen level produces no surface in the chosen region."""
