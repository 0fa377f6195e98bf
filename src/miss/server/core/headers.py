"""Security headers on every HTTP response, whatever answered it (a route, an error
handler, the rate limiter, Starlette's own 404 and 405).

The Content-Security-Policy lets a page run only MISS's own files: no inline script
(a page's import map is allowed by its SHA-256: the page sets the policy for the map it
sends, :func:`miss.server.core.assets.page`; other responses get the hashes of the pages' maps
as they are on disk),
no other origin for anything, no plug-ins, no framing (``frame-ancestors 'none'``: MISS
is never embedded; a share link opens in a tab of its own). ``'wasm-unsafe-eval'`` lets
three.js's meshopt decoder compile its WebAssembly (the glTF files use
EXT_meshopt_compression); it allows no JavaScript ``eval``. ReDoc alone needs inline
styles (it injects ``<style>`` elements) and a worker from a ``blob:`` URL, so ``/redoc``
gets exactly those two relaxations.
"""

from __future__ import annotations

import base64
import hashlib
import re
from pathlib import Path

from starlette.types import ASGIApp, Message, Receive, Scope, Send

_IMPORT_MAP = re.compile(r'<script type="importmap">(.*?)</script>', re.DOTALL)


def import_map_hashes(html: str) -> list[str]:
    """``'sha256-...'`` sources for the import maps of the page ``html``."""
    found = set()
    for block in _IMPORT_MAP.findall(html):
        digest = hashlib.sha256(block.encode("utf-8")).digest()
        found.add(f"'sha256-{base64.b64encode(digest).decode()}'")
    return sorted(found)


def inline_script_hashes(pages: Path) -> list[str]:
    """``'sha256-...'`` sources for the import maps of the HTML pages in ``pages``."""
    found = set()
    for page in sorted(pages.glob("*.html")):
        found.update(import_map_hashes(page.read_text(encoding="utf-8")))
    return sorted(found)


def policy(script_hashes: list[str], inline_styles: bool = False) -> str:
    """The Content-Security-Policy; ``inline_styles`` for ReDoc only."""
    style = "'self' 'unsafe-inline'" if inline_styles else "'self'"
    worker = "'self' blob:" if inline_styles else "'self'"
    scripts = " ".join(["'self'", "'wasm-unsafe-eval'", *script_hashes])
    return "; ".join(
        [
            "default-src 'self'",
            f"script-src {scripts}",
            f"style-src {style}",
            "img-src 'self' data: blob:",
            "font-src 'self' data:",
            "connect-src 'self'",
            f"worker-src {worker}",
            "object-src 'none'",
            "base-uri 'none'",
            "form-action 'self'",
            "frame-ancestors 'none'",
        ]
    )


#: Paths whose page needs inline styles (ReDoc).
INLINE_STYLE_PATHS = ("/redoc",)
PERMISSIONS = "camera=(), microphone=(), geolocation=(), payment=(), usb=()"
HSTS = "max-age=31536000; includeSubDomains"
CSP = b"content-security-policy"


class SecurityHeaders:
    """Pure ASGI middleware (so it sees every response, streamed ones too)."""

    def __init__(self, app: ASGIApp, pages: Path) -> None:
        self.app = app
        hashes = inline_script_hashes(pages)
        self.strict = policy(hashes).encode()
        self.relaxed = policy(hashes, inline_styles=True).encode()

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Add the security headers (CSP, nosniff, frame and referrer policies; HSTS over
        HTTPS) to every HTTP response."""
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        relaxed = scope["path"] in INLINE_STYLE_PATHS
        csp = (CSP, self.relaxed if relaxed else self.strict)
        extra = [
            (b"x-content-type-options", b"nosniff"),
            (b"referrer-policy", b"no-referrer"),
            (b"x-frame-options", b"DENY"),
            (b"cross-origin-opener-policy", b"same-origin"),
            (b"cross-origin-resource-policy", b"same-origin"),
            (b"permissions-policy", PERMISSIONS.encode()),
        ]
        if scope.get("scheme") == "https":
            extra.append((b"strict-transport-security", HSTS.encode()))
        names = {name for name, _ in extra}

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                kept = [(k, v) for k, v in message.get("headers", []) if k.lower() not in names]
                # a page's own policy (miss.server.core.assets.page: its import map as sent)
                own = any(k.lower() == CSP for k, _ in kept)
                message = {**message, "headers": kept + extra + ([] if own else [csp])}
            await send(message)

        await self.app(scope, receive, send_with_headers)
