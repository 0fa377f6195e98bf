"""Connections shared fairly, against a real ``miss serve`` over real sockets: uploads that
trickle or stall are stopped (408, nothing kept) and two accounts' slow uploads cannot
keep a third account's upload out; one account's event streams are capped; WebSocket
connects from one address are rate-limited; a deeply nested JSON room message gets a
clean error and leaves no traceback in the log."""

from __future__ import annotations

import json
import select
import socket
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx
import pytest
from support.pg import settings_for
from support.realserver import Server, serving
from support.server_app import running_row
from test_access import add_user, as_user, own_model, room, token_of
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from miss.server.core.settings import Settings
from miss.server.storage.store import Store

BOUNDARY = "trickle-boundary"
#: Sockets answered or left alone after this many half-second ticks (a bound, not a claim).
TICKS = 60
ENV = {
    "MISS_DEMO": "0",
    "MISS_UPLOAD_MIN_KBPS": "1",  # 1000 bytes/s: a byte per half second is far below
    "MISS_UPLOAD_RATE_SECONDS": "5",
    "MISS_UPLOAD_IDLE_SECONDS": "4",
    "MISS_SSE_PER_USER": "3",
    "MISS_WS_CONNECTS_PER_MINUTE": "20",
}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    folder = tmp_path_factory.mktemp("connections")
    with serving(folder / "data", folder / "server.log", env=ENV) as running:
        yield running


def start_upload(server: Server, token: str) -> socket.socket:
    """A multipart upload of a declared 100 kB whose headers and first part are sent;
    its file's bytes are left to the caller."""
    sock = socket.create_connection(("127.0.0.1", server.port), timeout=30)
    head = (
        f"POST /api/volumes HTTP/1.1\r\nHost: 127.0.0.1:{server.port}\r\n"
        f"Authorization: Bearer {token}\r\n"
        f"Content-Type: multipart/form-data; boundary={BOUNDARY}\r\n"
        "Content-Length: 100000\r\n\r\n"
        f"--{BOUNDARY}\r\n"
        'Content-Disposition: form-data; name="file"; filename="slow.nii.gz"\r\n\r\n'
    )
    sock.sendall(head.encode())
    return sock


def read_answer(sock: socket.socket) -> tuple[int, dict[str, Any]]:
    """(status, JSON body) of the response waiting on ``sock``; closes it."""
    data = b""
    with sock:
        sock.settimeout(30)
        while True:
            head, _, body = data.partition(b"\r\n\r\n")
            length = [
                int(line.split(b":")[1]) for line in head.split(b"\r\n")
                if line.lower().startswith(b"content-length:")
            ]  # fmt: skip
            if length and len(body) >= length[0]:
                break
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    status = int(head.split(b" ")[1])
    return status, json.loads(body or b"{}")


Answers = dict[int, tuple[int, dict[str, Any]]]


def trickle(socks: list[socket.socket], answers: Answers, until: Any = None) -> None:
    """Send each socket a byte every half second until the server answers it (its
    answer put in ``answers`` under its index), for ``TICKS`` at most; ``until()``, when
    given, is asked each tick and ends the trickling early when true."""
    for _ in range(TICKS):
        for n, sock in enumerate(socks):
            if n in answers:
                continue
            if select.select([sock], [], [], 0)[0]:
                answers[n] = read_answer(sock)
                continue
            try:
                sock.sendall(b"x")
            except OSError:  # answered and closed meanwhile: the answer is there to read
                answers[n] = read_answer(sock)
        if len(answers) == len(socks) or (until is not None and until()):
            return
        time.sleep(0.5)


def uploads_in(server: Server) -> int:
    """Uploads being received: each has a folder of its own under ``tmp/``."""
    tmp = server.data_dir / "tmp"
    return len(list(tmp.iterdir())) if tmp.exists() else 0


def test_trickling_uploads_of_two_accounts_do_not_block_a_third(
    server: Server, small_nifti: bytes
) -> None:
    """The finding: two accounts, two uploads each at 1 byte every 10 s, held all four
    upload slots for everyone, for ever."""
    tokens = {}
    for name in ("slowpoke", "dawdler", "carol"):
        add_user(server, name)
        tokens[name] = token_of(server, name)
    who = ("slowpoke", "slowpoke", "dawdler", "dawdler")
    socks = [start_upload(server, tokens[name]) for name in who]
    answers: Answers = {}
    # Until the server has taken (a folder each) or refused all four; bounded.
    trickle(socks, answers, until=lambda: uploads_in(server) + len(answers) >= len(socks))
    taken, refused = uploads_in(server), dict(answers)
    with ThreadPoolExecutor(1) as pool, as_user(server, tokens["carol"]) as carol:
        files = {"file": ("ball.nii.gz", small_nifti)}
        normal = pool.submit(carol.post, "/api/volumes", files=files, timeout=120)
        trickle(socks, answers)
        carol_status = normal.result().status_code
    # Whichever second upload came last found only the last free slot, kept for others.
    assert taken == 3 and len(refused) == 1, (taken, refused)
    [(second, (status, body))] = refused.items()
    assert status == 429 and "last free upload slot" in body["detail"], body
    assert carol_status == 201, "an account sending nothing found no free upload slot"
    for n in set(range(4)) - {second}:
        status, body = answers.get(n, (0, {}))
        assert status == 408, (n, status, body)
        assert "below the minimum of 1 kB/s" in body["detail"], body
    assert uploads_in(server) == 0  # the partial files are gone, and the slots free again
    with as_user(server, tokens["slowpoke"]) as again:
        r = again.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)}, timeout=120)
    assert r.status_code == 201, r.text


def test_a_stalled_upload_is_stopped(server: Server) -> None:
    """Headers and a little, then nothing: 408 after MISS_UPLOAD_IDLE_SECONDS."""
    sock = start_upload(server, server.token)
    readable = select.select([sock], [], [], 30)[0]
    assert readable, "a stalled upload was still waited for after 30 s"
    status, body = read_answer(sock)
    assert status == 408 and "no data for 4 s" in body["detail"], (status, body)
    assert uploads_in(server) == 0


def test_event_streams_per_account(server: Server, small_nifti: bytes) -> None:
    """The finding: an account could open event streams without end, each holding a
    connection and a polling task."""
    r = server.http.post("/api/volumes", files={"file": ("ball.nii.gz", small_nifti)})
    assert r.status_code == 201, r.text
    store = Store(server.data_dir, settings_for(server.data_dir).database_url)
    try:
        model = running_row(store, r.json()["id"])  # a job that stays running
    finally:
        store.close()
    url = f"{server.url}/api/models/{model}/events"
    headers = {"Authorization": f"Bearer {server.token}"}
    with httpx.Client(headers=headers, timeout=30) as http:
        streams = [http.stream("GET", url) for _ in range(3)]
        opened = [s.__enter__() for s in streams]
        try:
            assert [o.status_code for o in opened] == [200, 200, 200]
            over = http.get(url)
            assert over.status_code == 429, over.text
            assert "at most 3" in over.json()["detail"] and over.headers["Retry-After"]
            streams.pop().__exit__(None, None, None)  # closing one frees its place
            for _ in range(50):
                with http.stream("GET", url) as again:
                    if again.status_code == 200:
                        break
                time.sleep(0.2)
            assert again.status_code == 200
        finally:
            for s in streams:
                s.__exit__(None, None, None)


def connect_from(server: Server, address: str, model: str) -> tuple[int, str]:
    """Open a room connection from ``address`` without credentials: (close code, reason)."""
    sock = socket.create_connection(("127.0.0.1", server.port), 30, (address, 0))
    url = f"ws://127.0.0.1:{server.port}/ws/rooms/{model}"
    with connect(url, sock=sock, open_timeout=30) as ws:
        try:
            while True:
                ws.recv(timeout=30)
        except ConnectionClosed as closed:
            assert closed.rcvd is not None
            return closed.rcvd.code, closed.rcvd.reason
    raise AssertionError("unreachable")


def test_websocket_connects_from_one_address_are_limited(server: Server) -> None:
    """The finding: a loop could open room connections as fast as it liked, each one a
    database look-up and an audit entry."""
    model = own_model(server, server.token)
    closes = [connect_from(server, "127.0.0.77", model) for _ in range(30)]
    limited = [reason for code, reason in closes if code == 4429]
    assert len(limited) >= 5, closes
    assert "too many connections from your address" in limited[0], limited
    assert closes[0][0] == 4401  # the first ones were answered as usual: not logged in
    assert connect_from(server, "127.0.0.78", model)[0] == 4401  # other addresses go on


def test_deeply_nested_json_is_refused_without_a_traceback(server: Server) -> None:
    """The finding: ``[[[[...`` thousands deep raised RecursionError in the parser, which
    the room logged with its traceback as a server failure."""
    model = own_model(server, server.token)
    with room(server, model, token=server.token) as ws:
        ws.send("[" * 16000)  # under the 16 kB a message may have
        while (answer := json.loads(ws.recv(timeout=30)))["type"] != "error":
            pass
        assert answer["code"] == "malformed" and "nested too deeply" in answer["error"], answer
        ws.send(json.dumps({"type": "ping"}))  # the connection goes on
        while json.loads(ws.recv(timeout=30))["type"] != "pong":
            pass
    log = Path(server.log).read_text()
    assert "Traceback" not in log and "RecursionError" not in log


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("MISS_UPLOAD_MIN_KBPS", "-1"),
        ("MISS_UPLOAD_RATE_SECONDS", "0"),
        ("MISS_UPLOAD_IDLE_SECONDS", "0"),
        ("MISS_ROOM_RESERVED", "50"),
        ("MISS_ROOM_GUESTS_PER_LINK", "0"),
        ("MISS_SSE_PER_USER", "0"),
        ("MISS_WS_CONNECTS_PER_MINUTE", "0.5"),
    ],
)
def test_the_settings_say_what_is_wrong(tmp_path: Path, key: str, value: str) -> None:
    with pytest.raises(ValueError, match=key):
        Settings.from_env({key: value, "MISS_DATA_DIR": str(tmp_path)})


def test_a_small_room_keeps_fewer_places() -> None:
    """Rooms set small before the reserve existed still start: one place stays a guest's."""
    assert Settings.from_env({"MISS_ROOM_MAX_PEOPLE": "3"}).room_reserved == 2
    assert Settings.from_env({}).room_reserved == 5
