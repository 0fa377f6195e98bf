"""Live consultation rooms: one per model, joined over a WebSocket by its owner (or an
administrator) or by a share link that allows annotation.

The server relays and checks; the browsers draw. Positions travel in patient LPS
millimetres, so a participant in VRML mode and one in GLB mode point at the same anatomy.
Every message is JSON text of at most ``MAX_MESSAGE_BYTES``; each connection has a token
bucket (``BURST`` at once, ``RATE`` per second). Bad input gets an ``error`` frame naming
the problem and the connection stays; a client that keeps flooding, whose link expires or
is revoked, or that reads too slowly is closed with a code saying why. Nobody else in the
room notices any of it.

Each participant has an outgoing queue drained by its own task, so one slow browser
never holds up a broadcast to the others.

Places: guests fill at most ``max_people - reserved`` of a room, and at most
``per_link`` through one link, so the guests of one leaked link cannot lock out the
owner, the administrators or the guests of the owner's other links. What people see of
each other is display names, colours and a per-room pseudonym (:func:`public_key`): never
an account's id or another link's id.
"""

from miss.server.rooms.hub import GUESTS_PER_LINK, MAX_PEOPLE, RESERVED, Hub
from miss.server.rooms.people import (
    BURST,
    MAX_MESSAGE_BYTES,
    RATE,
    Close,
    Invalid,
    Participant,
    Refused,
    Visitor,
    guest_name,
    public_key,
)
from miss.server.rooms.room import Room

__all__ = [
    "BURST",
    "GUESTS_PER_LINK",
    "MAX_MESSAGE_BYTES",
    "MAX_PEOPLE",
    "RATE",
    "RESERVED",
    "Close",
    "Hub",
    "Invalid",
    "Participant",
    "Refused",
    "Room",
    "Visitor",
    "guest_name",
    "public_key",
]
