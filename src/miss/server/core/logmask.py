"""Keep credentials out of the logs: share-link tokens travel in URL paths and queries.

uvicorn's access log prints every path; a share token there would let anyone who reads
the log open the link. The filter rewrites the record before any handler formats it.
"""

from __future__ import annotations

import logging
import re

_TOKENS = re.compile(r"(/s/|[?&](?:share|token)=)[A-Za-z0-9_\-]{8,}")


def mask(text: str) -> str:
    """``/s/AbC…xyz/model.glb`` -> ``/s/…/model.glb``; the same for ``?share=`` values."""
    return _TOKENS.sub(r"\1…", text)


class MaskTokens(logging.Filter):
    """A logging filter that masks tokens in the message and its string arguments."""

    def filter(self, record: logging.LogRecord) -> bool:
        """Mask tokens in the record's message and arguments; always keeps the record."""
        if isinstance(record.msg, str):
            record.msg = mask(record.msg)
        if isinstance(record.args, tuple):
            record.args = tuple(mask(a) if isinstance(a, str) else a for a in record.args)
        return True


def install(*loggers: str) -> None:
    """Add the filter to the named loggers (uvicorn's access and error logs)."""
    for name in loggers:
        logger = logging.getLogger(name)
        if not any(isinstance(f, MaskTokens) for f in logger.filters):
            logger.addFilter(MaskTokens())
