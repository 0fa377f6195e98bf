"""Room places and presence, against a real ``miss serve`` over real sockets: the guests
of one link cannot fill a room and lock its owner out; guests as a whole leave the
reserved places free; what a guest hears of the others is display names, never an
account's id or another link's id."""

from __future__ import annotations

import contextlib
import json
from collections.abc import Iterator
from typing import Any
from urllib.parse import quote

import pytest
from support.realserver import Server, serving
from test_access import add_user, as_user, own_model, pin_at_centre, room, token_of
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import ClientConnection, connect

# Defaults of the room places (50 people, 5 kept, 20 a link); connects not limited here.
ENV = {"MISS_DEMO": "0", "MISS_WS_CONNECTS_PER_MINUTE": "1000"}


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    folder = tmp_path_factory.mktemp("rooms")
    with serving(folder / "data", folder / "server.log", env=ENV) as running:
        yield running


@pytest.fixture(scope="module")
def owner(server: Server) -> str:
    """The token of alice, who owns the models of this module."""
    add_user(server, "alice")
    return token_of(server, "alice")


def link(server: Server, token: str, model: str) -> dict[str, Any]:
    with as_user(server, token) as http:
        r = http.post("/api/shares", json={"model": model, "can_annotate": True})
    assert r.status_code == 201, r.text
    return r.json() | {"token": r.json()["url"][3:]}


def join(
    stack: contextlib.ExitStack, server: Server, model: str, share: str, name: str = "guest"
) -> tuple[ClientConnection | None, dict[str, Any]]:
    """A guest's attempt: (the open connection, its welcome), or (None, {code, reason})."""
    url = f"ws://127.0.0.1:{server.port}/ws/rooms/{model}?share={share}&name={quote(name)}"
    ws = stack.enter_context(connect(url, open_timeout=30))
    first = json.loads(ws.recv(timeout=30))
    if first["type"] == "welcome":
        return ws, first
    try:
        while True:
            ws.recv(timeout=30)
    except ConnectionClosed as closed:
        assert closed.rcvd is not None
        return None, {"code": closed.rcvd.code, "reason": closed.rcvd.reason}


def test_one_links_guests_do_not_lock_the_owner_out(server: Server, owner: str) -> None:
    """The finding: one annotate link's 50 guests filled the room; its owner and the
    administrators could not get in."""
    model = own_model(server, owner)
    share = link(server, owner, model)["token"]
    with contextlib.ExitStack() as stack:
        tries = [join(stack, server, model, share) for _ in range(50)]
        refused = [why for ws, why in tries if ws is None]
        assert len(tries) - len(refused) == 20, refused
        assert {why["code"] for why in refused} == {4429}
        assert "this link already has 20 guests" in refused[0]["reason"], refused[0]
        with room(server, model, token=owner) as mine, room(server, model, token=server.token):
            assert mine.welcome["you"]["owner"]  # type: ignore[attr-defined]


def test_guests_leave_the_reserved_places(server: Server, owner: str) -> None:
    """Guests of several links together take at most 45 of the 50 places."""
    model = own_model(server, owner)
    shares = [link(server, owner, model)["token"] for _ in range(3)]
    with contextlib.ExitStack() as stack:
        for share in shares[:2]:
            assert all(join(stack, server, model, share)[0] for _ in range(20))
        last = [join(stack, server, model, shares[2]) for _ in range(10)]
        refused = [why for ws, why in last if ws is None]
        assert len(refused) == 5, refused
        assert "all 45 places for guests in this room are taken" in refused[0]["reason"]
        with room(server, model, token=owner), room(server, model, token=server.token):
            pass


def test_guests_hear_names_not_ids(server: Server, owner: str) -> None:
    """The finding: presence told guests the owner's user id (``u:<id>``) and every
    other guest's link id (``s:<share id>:...``), in the people list and in each pin."""
    alice = next(u for u in server.http.get("/api/users").json() if u["name"] == "alice")
    model = own_model(server, owner)
    mine, other = link(server, owner, model), link(server, owner, model)
    heard: list[str] = []
    with contextlib.ExitStack() as stack:
        host = stack.enter_context(room(server, model, token=owner))
        pin_at_centre(host, model)
        join(stack, server, model, other["token"], "Dr Other")
        ws, welcome = join(stack, server, model, mine["token"], "Dr Guest")
        assert ws is not None
        heard.append(json.dumps(welcome))
        join(stack, server, model, other["token"], "Dr Late")
        pin_at_centre(host, model)
        host.send(json.dumps({"type": "chat", "text": "that is all"}))
        while True:
            heard.append(ws.recv(timeout=30))
            if json.loads(heard[-1])["type"] == "chat":
                break
    said = "\n".join(heard)
    assert "alice" in said and "Dr Other (guest)" in said and "Dr Late (guest)" in said
    for secret in (alice["id"], other["id"], mine["id"]):
        assert secret not in said, f"a guest heard the id {secret}"
    assert '"u:' not in said and '"s:' not in said
