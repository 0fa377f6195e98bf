"""MISS exceptions: each message names the problem and the fix.

The CLI prints ``str(exc)`` on one line and exits with code 2; the server answers
4xx with the message as ``detail``.
"""

from __future__ import annotations

import errno


class MissError(Exception):
    """Base class for every error MISS raises on purpose (bad input, bad parameter)."""


class UnreadableVolume(MissError, ValueError):
    """A file or folder that cannot be read as a volume (missing, truncated, wrong magic)."""


class UnreadableSegmentation(UnreadableVolume):
    """A DICOM SEG or RT-STRUCT that cannot be laid over its series (not one, no segments,
    no geometry, contours off the image planes)."""


class UnsupportedFormat(MissError, ValueError):
    """A file extension or format MISS has no reader or writer for."""


class BadParameter(MissError, ValueError):
    """A processing parameter out of range (sample rate, slices, reduce, level ...)."""


class EmptySurface(MissError, ValueError):
    """The chosen level produces no surface in the chosen region."""


class InputTooLarge(MissError, ValueError):
    """An upload, or the files a zip expands to, over the configured limit."""


class UnsafeArchive(UnreadableVolume):
    """A zip with members that would land outside its folder (``../``, absolute, links),
    or that inflates far beyond what scans compress to (a zip bomb)."""


class DiskFull(MissError, RuntimeError):
    """No room left for an upload or a job in the data folder: 507 Insufficient Storage."""


class PacsError(MissError, RuntimeError):
    """A PACS that did not answer, answered with an error, or sent something that is not
    what was asked for: 502 Bad Gateway (the message names the PACS and what to check)."""


class PacsTimeout(PacsError):
    """A PACS that took longer than the timeout: 504 Gateway Timeout (try again later)."""


class WrongStudy(MissError, ValueError):
    """A model that would be filed where it does not belong: a volume not imported from
    that PACS, or a study that no longer has the patient or series it was made from
    (409 Conflict; nothing is stored). ``study``: the study it would have gone into."""

    def __init__(self, message: str, study: str = "") -> None:
        super().__init__(message)
        self.study = study


def is_disk_full(exc: BaseException) -> bool:
    """True for "no space left on device" (or over a disk quota)."""
    if not isinstance(exc, OSError):
        return False
    # numpy's np.save / tofile says it in words, without an errno.
    return exc.errno in (errno.ENOSPC, errno.EDQUOT) or str(exc).startswith(
        "Not enough free space to write"
    )
