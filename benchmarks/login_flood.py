"""Another user's API latency while 120 logins arrive at once (issue 39).

A logged-in user asks ``GET /api/auth/me`` every 50 ms while 120 clients, each from a
loopback address and under a name of its own (so no login limit refuses them), log in
with a wrong password at the same moment: each costs an argon2id check (64 MiB, tens of
ms of a core). Prints the user's latencies before and during the flood and how the
logins were answered. Run it against old code with ``PYTHONPATH=<old>/src``.

    python benchmarks/login_flood.py
"""

from __future__ import annotations

import statistics
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
from load import log_in, start_server, stop_server

LOGINS = 120


def probe(url: str, headers: dict[str, str], seconds: float) -> list[float]:
    """Latencies (s) of ``GET /api/auth/me``, one every 50 ms for ``seconds``."""
    out, end = [], time.monotonic() + seconds
    with httpx.Client(base_url=url, headers=headers, timeout=60) as http:
        while time.monotonic() < end:
            start = time.perf_counter()
            http.get("/api/auth/me").raise_for_status()
            out.append(time.perf_counter() - start)
            time.sleep(0.05)
    return out


def guess(url: str, n: int) -> int:
    transport = httpx.HTTPTransport(local_address=f"127.0.{1 + n // 200}.{10 + n % 200}")
    with httpx.Client(base_url=url, transport=transport, timeout=120) as http:
        body = {"username": f"flood{n}", "password": "not-the-password"}
        return http.post("/api/auth/login", json=body).status_code


def row(name: str, values: list[float]) -> str:
    ms = sorted(v * 1000 for v in values)
    p95 = ms[int(0.95 * (len(ms) - 1))]
    return f"| {name} | {len(ms)} | {statistics.median(ms):.0f} | {p95:.0f} | {ms[-1]:.0f} |"


def main() -> None:
    folder = Path(tempfile.mkdtemp(prefix="miss-flood-"))
    proc, url = start_server(folder / "data", workers=1)
    try:
        headers = log_in(url, "admin")
        quiet = probe(url, headers, 3.0)
        during: list[float] = []
        worker = threading.Thread(target=lambda: during.extend(probe(url, headers, 15.0)))
        worker.start()
        start = time.monotonic()
        with ThreadPoolExecutor(LOGINS) as pool:
            codes = list(pool.map(lambda n: guess(url, n), range(LOGINS)))
        took = time.monotonic() - start
        worker.join()
    finally:
        stop_server(proc)
    print("| another user's GET /api/auth/me | requests | median ms | p95 ms | max ms |")
    print("|---|---|---|---|---|")
    print(row("quiet", quiet))
    print(row(f"during {LOGINS} logins", during))
    answered = {code: codes.count(code) for code in sorted(set(codes))}
    print(f"\nlogins answered {answered} in {took:.1f} s")


if __name__ == "__main__":
    main()
