"""What a correct refusal message and a correct loaded volume look like.

Shared by the corpus and fuzz tests (and usable by anything that pushes the corpus
through another door, e.g. the HTTP upload API's ``detail``).
"""

from __future__ import annotations

import re

import numpy as np

from miss.types import Volume

#: Words a message uses to tell the user what to do.
FIX = re.compile(
    r"\b(copy|check|pass|use|export|fix|re-\w+|install|upload|put|rename|convert|zip|add|"
    r"remove|download|save|create|leave|give)\b",
    re.IGNORECASE,
)
#: Python internals that must not reach a user: tracebacks, reprs, exception class names.
NOISE = re.compile(
    r"Traceback|File \"|<[^<>]* at 0x[0-9a-f]+>|\b[A-Z][a-z]\w*(Error|Exception|Warning)\b"
)


def message_problems(text: str, name: str = "") -> list[str]:
    """What is wrong with a refusal message (empty when it is fine).

    It must be one line of valid text, name the input (``name``, when given) and a fix,
    and carry no Python internals.
    """
    problems = []
    if not text.strip() or "\n" in text.strip():
        problems.append("not exactly one line")
    noise = NOISE.search(text)
    if noise:
        problems.append(f"Python internals ({noise.group(0)!r})")
    if not FIX.search(text):
        problems.append("names no fix")
    if name and name not in text:
        problems.append(f"does not name {name}")
    try:
        text.encode("utf-8")
    except UnicodeEncodeError:
        problems.append("not valid text (lone surrogates)")
    return problems


def volume_problems(vol: Volume) -> list[str]:
    """What is wrong with a loaded volume (empty when it is fine): 3-D with at least 2
    voxels per axis, real finite voxels, a finite and non-degenerate affine."""
    problems = []
    if vol.data.ndim != 3 or min(vol.data.shape) < 2:
        problems.append(f"shape {vol.data.shape}")
    if vol.data.dtype.kind not in "iuf":
        problems.append(f"dtype {vol.data.dtype}")
    elif vol.data.dtype.kind == "f" and not np.isfinite(vol.data).all():
        problems.append("non-finite voxels")
    steps = np.linalg.norm(vol.affine[:3, :3], axis=0)
    if not np.isfinite(vol.affine).all():
        problems.append("non-finite affine")
    elif steps.min() <= 0 or abs(np.linalg.det(vol.affine[:3, :3])) < 1e-6 * steps.prod():
        problems.append(f"degenerate affine {vol.affine[:3, :3].tolist()}")
    return problems
