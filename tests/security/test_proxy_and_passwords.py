"""Client addresses and password checks, against a real ``miss serve``.

The findings: uvicorn believed ``X-Forwarded-For`` from 127.0.0.1 by default, so a
client on the machine (or behind a proxy that passes the header on) named a new address
with each login and skipped every per-address limit; and each of 120 such logins checked
a password (argon2id) at once, so another user's requests waited 8.3 s. Now only the
proxies ``MISS_TRUSTED_PROXIES`` names are believed, and a server process checks at most
``MISS_PASSWORD_CHECKS`` passwords at once; the logins beyond wait a little, then 429."""

from __future__ import annotations

import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest
from support import ADMIN_PASSWORD
from support.realserver import Server, serving

WRONG = "not-the-password"
#: Seconds a login waits for its turn at the password check (``ratelimit.PASSWORD_WAIT``).
PASSWORD_WAIT = 5.0


def log_in(server: Server, name: str, source: str, forwarded: str = "") -> httpx.Response:
    """A login from the loopback address ``source``, naming ``forwarded`` as the client."""
    headers = {"X-Forwarded-For": forwarded} if forwarded else {}
    transport = httpx.HTTPTransport(local_address=source)
    with httpx.Client(base_url=server.url, transport=transport, timeout=120) as http:
        body = {"username": name, "password": WRONG if name != "admin" else ADMIN_PASSWORD}
        return http.post("/api/auth/login", json=body, headers=headers)


def audited_address(server: Server, count: int) -> list[str]:
    """The addresses of the newest failed logins, once ``count`` are written (the audit
    is written just after each answer)."""
    for _ in range(100):
        entries = server.http.get("/api/audit", params={"action": "login_failed"}).json()
        if len(entries) >= count:
            return [e["address"] for e in entries]
        time.sleep(0.1)
    raise AssertionError(f"fewer than {count} failed logins audited: {entries}")


def test_forwarded_for_is_not_believed_by_default(tmp_path: Path) -> None:
    with serving(tmp_path / "data", tmp_path / "server.log", env={"MISS_DEMO": "0"}) as server:
        codes = [
            log_in(server, f"nobody{n}", "127.0.0.1", forwarded=f"203.0.113.{n}").status_code
            for n in range(12)
        ]
        addresses = audited_address(server, 10)
    # One client, whatever it says it is: ten failed logins, then locked out.
    assert codes == [401] * 10 + [429, 429], codes
    assert set(addresses) == {"127.0.0.1"}, addresses


@pytest.fixture(scope="module")
def proxied(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """A server behind a proxy at 127.0.0.2 that checks one password at a time."""
    folder = tmp_path_factory.mktemp("proxied")
    env = {"MISS_DEMO": "0", "MISS_TRUSTED_PROXIES": "127.0.0.2", "MISS_PASSWORD_CHECKS": "1"}
    with serving(folder / "data", folder / "server.log", env=env) as running:
        yield running


def test_only_the_named_proxy_is_believed(proxied: Server) -> None:
    assert log_in(proxied, "via-proxy", "127.0.0.2", "198.51.100.7").status_code == 401
    assert log_in(proxied, "not-via-proxy", "127.0.0.1", "198.51.100.8").status_code == 401
    addresses = audited_address(proxied, 2)
    assert addresses[-2:] == ["198.51.100.7", "127.0.0.1"], addresses


def test_password_checks_wait_their_turn(proxied: Server) -> None:
    """Logins at once, each from an address and under a name of its own (no login limit
    refuses them), three times as many as one check at a time gets through in the 5 s a
    login may wait: those that waited too long are told to come back, none fails
    otherwise. Without the cap every password is checked at once, all answered 401."""

    def guess(n: int) -> httpx.Response:
        return log_in(proxied, f"flood{n}", f"127.0.{1 + n // 200}.{10 + n % 200}")

    timed = []
    for n in range(3):  # how long one check takes here, from a login's round trip
        start = time.perf_counter()
        assert guess(1000 + n).status_code == 401
        timed.append(time.perf_counter() - start)
    many = min(400, int(3 * PASSWORD_WAIT / sorted(timed)[1]) + 40)
    with ThreadPoolExecutor(many) as pool:
        answers = list(pool.map(guess, range(many)))
    codes = [a.status_code for a in answers]
    busy = [a for a in answers if a.status_code == 429]
    assert set(codes) <= {401, 429}, codes
    assert busy, "every password was checked at once (MISS_PASSWORD_CHECKS=1)"
    assert all(int(a.headers["Retry-After"]) >= 1 for a in busy)
    assert all("MISS_PASSWORD_CHECKS" in a.json()["detail"] for a in busy), busy[0].text
    assert codes.count(401) >= 1
    # Those told to wait lost no try: the next login of the same names is checked.
    assert log_in(proxied, "admin", "127.0.0.3").status_code == 200


@pytest.mark.parametrize(
    ("name", "value", "says"),
    [
        ("MISS_TRUSTED_PROXIES", "proxy.local", "not an IP address or network"),
        ("MISS_TRUSTED_PROXIES", "10.0.0.1, 10.0.0.300", "'10.0.0.300'"),
        ("MISS_PASSWORD_CHECKS", "0", "at least 1"),
    ],
)
def test_bad_settings_are_named(name: str, value: str, says: str) -> None:
    from miss.server.core.settings import Settings

    with pytest.raises(ValueError, match=name) as refused:
        Settings.from_env({name: value})
    assert says in str(refused.value)
    assert Settings.from_env({name: "127.0.0.1, 10.0.0.0/24" if "PROX" in name else "3"})
