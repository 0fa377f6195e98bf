"""The pages' files (MISS's JS and CSS, and the npm packages they use) under URLs that
name their version, which a browser keeps without asking again.

A page is sent with its ``/static/`` and ``/vendor/`` URLs, its import map's too, moved
under ``/v/<version>/``. The version is a digest of the size and modification time of
every file of the web folder and of each package's ``package.json`` (npm rewrites it at
each install). A file asked for under the current version is sent ``immutable`` for a
year: the next time a page needs it, the browser takes its own copy and the code it
compiled from it, with no request. Before, each of the viewer's ~30 modules was asked
again at each page (``no-cache``), on a server busy making the model the page waits for:
0.4 s of requests on the 2-core test machine, before the page could start.

An edited file makes a new version, so the next page asks for the new files. A file
asked for under another version (a page sent before the edit) is sent as it is now,
``no-cache``: nothing a browser keeps for a year can differ from what its version names.
The plain ``/static/`` and ``/vendor/`` URLs answer as before, for scripts and tests.
"""

from __future__ import annotations

import functools
import hashlib
import os
import re
from pathlib import Path

from starlette.responses import Response

import miss

WEB = Path(miss.__file__).parent / "web"
MODULES = WEB / "node_modules"
#: npm packages served under /vendor/NAME/ (only the files they ship for browsers), and
#: the folder whose ``package.json`` names the installed copy.
VENDOR = {
    "three": (MODULES / "three", MODULES / "three"),
    "swagger-ui": (MODULES / "swagger-ui-dist", MODULES / "swagger-ui-dist"),
    "redoc": (MODULES / "redoc" / "bundles", MODULES / "redoc"),
}
#: How long a browser keeps a file under its version: a year, without asking.
KEEP = "public, max-age=31536000, immutable"
#: A URL of a page's own files, in an attribute or the import map (a quote before it).
_URL = re.compile(r"""(?<=["'])/(static|vendor)/""")


def version() -> str:
    """The current version of the pages' files: 12 hex digits (about 0.5 ms to find)."""
    digest = hashlib.blake2b(digest_size=6)
    stats = []
    for root, dirs, files in os.walk(WEB):
        dirs[:] = sorted(d for d in dirs if Path(root, d) != MODULES)
        stats += [os.path.join(root, name) for name in sorted(files)]
    stats += [str(installed / "package.json") for _, installed in VENDOR.values()]
    for path in stats:
        try:
            st = os.stat(path)
        except OSError:  # a package not installed: its URLs answer 404 whatever the version
            continue
        digest.update(f"{path}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return digest.hexdigest()


def versioned(html: str, current: str) -> str:
    """``html`` with its ``/static/`` and ``/vendor/`` URLs under ``/v/<current>/``."""
    return _URL.sub(lambda m: f"/v/{current}/{m.group(1)}/", html)


@functools.lru_cache(maxsize=32)
def _page(name: str, current: str) -> tuple[bytes, str, str]:
    from miss.server.core.headers import import_map_hashes, policy

    html = versioned((WEB / name).read_text(encoding="utf-8"), current)
    hashes = import_map_hashes(html)
    return html.encode("utf-8"), policy(hashes), policy(hashes, inline_styles=True)


def page(name: str, headers: dict[str, str] | None = None, inline_styles: bool = False) -> Response:
    """The page ``web/<name>`` with its files' URLs under the current version, and the
    Content-Security-Policy that allows its import map as sent (``inline_styles``: the
    policy ReDoc needs). ``headers``: more (default: ``no-cache``, asked for each time)."""
    body, strict, relaxed = _page(name, version())
    return Response(
        body,
        media_type="text/html",
        headers={
            "Cache-Control": "no-cache",
            **(headers or {}),
            "Content-Security-Policy": relaxed if inline_styles else strict,
        },
    )
