r"""Where the login may send a browser afterwards: one rule, applied by the server.

A ``next`` value is read as a browser's URL parser (the WHATWG URL standard, as chromium
and firefox implement it) would resolve it against this site, and accepted only when it
stays a path on this site. The pages never judge ``next`` themselves: the login answers
the checked path and the page goes there (see ``routes/auth.py``).

What browsers do that a naive check misses: they drop tabs and newlines anywhere, read
``\`` as ``/``, decode ``%2e`` as a dot in ``.`` and ``..`` segments and remove those
segments, so ``/.//evil.example``, ``/%2e//evil.example`` and ``/a/..//evil.example``
all become the path ``//evil.example``, which a later navigation to that path reads as
another host. So the check runs on the resolved path, not on the text.
"""

from __future__ import annotations

from urllib.parse import quote

#: Longer values are not a page of MISS (its own paths are far shorter): sent home.
MAX_NEXT = 2048
#: Where a refused ``next`` leads.
HOME = "/"

_C0_AND_SPACE = "".join(map(chr, range(0x21)))
_TAB_NEWLINE = str.maketrans("", "", "\t\n\r")
_SINGLE_DOT = frozenset({".", "%2e"})
_DOUBLE_DOT = frozenset({"..", ".%2e", "%2e.", "%2e%2e"})
#: Kept as they are in a path, query or fragment; everything else is percent-encoded
#: (control characters, spaces, quotes, non-ASCII), so the answer parses as itself.
_PATH_SAFE = "!$%&'()*+,;=:@-._~"
_QUERY_SAFE = _PATH_SAFE + "/?"


def safe_next(target: str) -> str:
    r"""The path on this site that ``target`` leads to, else ``"/"``.

    Parameters
    ----------
    target : str
        The ``next`` value as the browser had it (already URL-decoded once, as
        ``URLSearchParams`` and Starlette's query parameters give it).

    Returns
    -------
    str
        ``"/"`` or a path that starts with one ``/`` followed by neither ``/`` nor ``\``,
        holds no dot segments, no backslash and no control character or space, with its
        query and fragment: a browser resolves it to this site, and to itself.
    """
    if len(target) > MAX_NEXT:
        return HOME
    text = target.strip(_C0_AND_SPACE).translate(_TAB_NEWLINE)
    # Anything else is a scheme ("https:", "javascript:", "data:"), an authority ("//",
    # "\\\\", "/\\") or a relative path: none of them is wanted after a login.
    if text[:1] not in ("/", "\\") or text[1:2] in ("/", "\\"):
        return HOME
    path, query, fragment = _split(text)
    segments = _resolve(path.replace("\\", "/")[1:].split("/"))
    if segments[:1] == [""] and len(segments) > 1:
        return HOME  # "//host...": the path starts with an empty segment
    out = "/" + "/".join(quote(s, safe=_PATH_SAFE) for s in segments)
    if query is not None:
        out += "?" + quote(query, safe=_QUERY_SAFE)
    if fragment is not None:
        out += "#" + quote(fragment, safe=_QUERY_SAFE + "#")
    return out


def _split(text: str) -> tuple[str, str | None, str | None]:
    """(path, query, fragment) as a URL parser splits them: at the first "#", then "?"."""
    text, hashed, fragment = text.partition("#")
    path, asked, query = text.partition("?")
    return path, query if asked else None, fragment if hashed else None


def _resolve(parts: list[str]) -> list[str]:
    """The path's segments with ``.`` and ``..`` (in any spelling) applied, as the URL
    standard's path state does: a last dot segment leaves an empty one ("/a/.." is "/")."""
    segments: list[str] = []
    for i, part in enumerate(parts):
        last = i == len(parts) - 1
        lowered = part.lower()
        if lowered in _DOUBLE_DOT:
            if segments:
                segments.pop()
            if last:
                segments.append("")
        elif lowered in _SINGLE_DOT:
            if last:
                segments.append("")
        else:
            segments.append(part)
    return segments or [""]
