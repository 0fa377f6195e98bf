"""What clients send a room: each message type's handler, and the checks of its fields
(points in patient mm, texts of bounded length, ids of the room's own items)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from miss.server.rooms.people import MAX_NAME, Invalid, Participant, guest_name, public_item
from miss.server.rooms.room import Room

if TYPE_CHECKING:
    from miss.server.rooms.hub import Hub

MAX_NOTE, MAX_CHAT = 500, 2000
#: Parts a display state may describe (a label map's structures are at most 255).
MAX_PARTS = 512
CLIP_AXES = ("axial", "coronal", "sagittal")
#: The presenter's camera goes to the replay at most this often (seconds).
VIEW_EVERY = 1.0


def point(value: Any, name: str) -> list[float]:
    """Three finite numbers (patient mm)."""
    numbers = (
        isinstance(value, list)
        and len(value) == 3
        and all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    )
    if numbers and all(math.isfinite(v) and abs(v) < 1e6 for v in value):
        return [float(v) for v in value]
    raise Invalid("invalid", f"{name} must be [x, y, z]: three finite numbers in millimetres.")


def text(value: Any, name: str, limit: int, required: bool = True) -> str:
    """``value`` if it is a string of at most ``limit`` characters (non-blank when
    ``required``; None gives "" when not); Invalid naming ``name`` otherwise."""
    if value is None and not required:
        return ""
    if not isinstance(value, str) or (required and not value.strip()):
        raise Invalid("invalid", f"{name} must be a non-empty string.")
    if len(value) > limit:
        raise Invalid("invalid", f"{name} is {len(value)} characters long; at most {limit}.")
    return value.strip()


def event_id(value: Any, known: dict[int, Any], what: str) -> int:
    """``value`` if it is the id of an item in ``known``; Invalid naming ``what`` otherwise."""
    if not isinstance(value, int) or isinstance(value, bool) or value not in known:
        raise Invalid("invalid", f"no {what} with id {value!r} in this room.")
    return value


Handler = Callable[["Hub", Room, Participant, dict[str, Any]], Awaitable[None]]


def _check_model(room: Room, message: dict[str, Any]) -> None:
    target = message.get("model")
    if target is not None and target != room.model_id:
        raise Invalid(
            "wrong_model",
            f"this room is model {room.model_id!r}; refused an item for model {target!r} "
            "(open that model's room to annotate it).",
        )


async def on_ping(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """Answer a ping with a pong (a client's keep-alive)."""
    person.send({"type": "pong"})


async def on_presenter(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """Make the sender the presenter (``on``) or stop presenting; tell everyone and record it."""
    on = message.get("on")
    if not isinstance(on, bool):
        raise Invalid("invalid", '"on" must be true (present) or false (stop presenting).')
    if on:
        room.presenter, room.view = person.id, None
    elif room.presenter == person.id:
        room.presenter, room.view = None, None
    else:
        return
    name = person.visitor.name if on else None
    hub.broadcast(room, {"type": "presenter", "id": room.presenter, "name": name})
    await hub.store_event(room, person, "presenter", {"on": on})


async def on_camera(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """Share the presenter's camera (position, target, up in patient mm) with the others;
    Invalid when the sender is not the presenter."""
    if room.presenter != person.id:
        raise Invalid("not_presenter", "only the presenter's view is shared; press Present first.")
    view = {k: point(message.get(k), k) for k in ("position", "target", "up")}
    room.view = view
    hub.broadcast(room, {"type": "camera", "from": person.id, **view}, skip=person)
    now = time.monotonic()
    if now - room.last_view >= VIEW_EVERY:  # the replay gets a view a second, not sixty
        room.last_view = now
        await hub.store_event(room, person, "view", view)


def fraction(value: Any, name: str) -> float:
    """A finite number in [0, 1]."""
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if ok and math.isfinite(value) and 0.0 <= value <= 1.0:
        return float(value)
    raise Invalid("invalid", f"{name} must be a number from 0 to 1.")


def display_state(message: dict[str, Any]) -> dict[str, Any]:
    """``parts`` (each part's ``visible`` and ``opacity``, in the model's order),
    ``clip`` (null, or an ``axis`` and the ``fraction`` of the extent kept), ``volume``
    (:func:`volume_view`) and ``slices`` (:func:`linked_slices`), checked."""
    parts = message.get("parts")
    if not isinstance(parts, list) or len(parts) > MAX_PARTS:
        raise Invalid("invalid", f"parts must be a list of at most {MAX_PARTS} parts.")
    shown = []
    for n, part in enumerate(parts):
        if not isinstance(part, dict) or not isinstance(part.get("visible"), bool):
            raise Invalid("invalid", f"parts[{n}] must be {{visible: true|false, opacity: 0..1}}.")
        shown.append(
            {"visible": part["visible"], "opacity": fraction(part.get("opacity"), "opacity")}
        )
    clip = message.get("clip")
    if clip is not None:
        if not isinstance(clip, dict) or clip.get("axis") not in CLIP_AXES:
            raise Invalid(
                "invalid", f"clip must be null or {{axis: {'|'.join(CLIP_AXES)}, fraction}}."
            )
        clip = {"axis": clip["axis"], "fraction": fraction(clip.get("fraction"), "clip fraction")}
    return {
        "parts": shown,
        "clip": clip,
        "volume": volume_view(message.get("volume")),
        "slices": linked_slices(message.get("slices")),
    }


def linked_slices(value: Any) -> dict[str, Any] | None:
    """The linked slices beside the 3-D view (issue 43): null, or ``on`` and the
    crosshair's ``point`` (patient LPS mm, or null before the scan came), checked."""
    if value is None:
        return None
    if not isinstance(value, dict) or not isinstance(value.get("on"), bool):
        raise Invalid("invalid", "slices must be null or {on: true|false, point: [x, y, z]}.")
    at = value.get("point")
    return {"on": value["on"], "point": None if at is None else point(at, "slices point")}


#: The longest name of a volume preset ("CT bone", "MR T1 head", ...) a display may carry.
MAX_PRESET = 40


def number(value: Any, name: str, positive: bool = False) -> float:
    """A finite number below 1e6 in size (above 0 when ``positive``): a level or window
    in the volume's units (HU for CT)."""
    ok = isinstance(value, int | float) and not isinstance(value, bool)
    if ok and math.isfinite(value) and abs(value) < 1e6 and (value > 0 or not positive):
        return float(value)
    kind = "a positive number" if positive else "a number"
    raise Invalid("invalid", f"{name} must be {kind} below 1e6 in the volume's units.")


def volume_view(value: Any) -> dict[str, Any] | None:
    """The scan's view in the 3-D scene (issue 43): null, or ``on``, the ``preset``, the
    ``level`` and ``window`` (the volume's units) and an edited transfer function's
    ``points`` (:func:`transfer_points`), checked."""
    if value is None:
        return None
    if not isinstance(value, dict) or not isinstance(value.get("on"), bool):
        raise Invalid("invalid", "volume must be null or {on: true|false, preset, level, window}.")
    view: dict[str, Any] = {"on": value["on"], "level": None, "window": None}
    view["preset"] = text(value.get("preset"), "volume preset", MAX_PRESET, required=False) or None
    # Level and window go together: one without the other is not a window.
    if value.get("level") is not None or value.get("window") is not None:
        view["level"] = number(value.get("level"), "volume level")
        view["window"] = number(value.get("window"), "volume window", positive=True)
    view["points"] = transfer_points(value.get("points"))
    return view


#: Most points an edited transfer function may have (js/viewer/tf-editor.js MAX_POINTS).
MAX_POINTS = 32


def transfer_points(value: Any) -> list[list[float]] | None:
    """An edited transfer function: null, or 2 to :data:`MAX_POINTS` points ``[value, r, g,
    b, opacity]``, values (the volume's units) in increasing order, the rest from 0 to 1."""
    if value is None:
        return None
    shape = f"points must be null or 2 to {MAX_POINTS} [value, r, g, b, opacity] in value order."
    if not isinstance(value, list) or not 2 <= len(value) <= MAX_POINTS:
        raise Invalid("invalid", shape)
    points: list[list[float]] = []
    for n, p in enumerate(value):
        if not isinstance(p, list) or len(p) != 5:
            raise Invalid("invalid", shape)
        at = number(p[0], f"points[{n}] value")
        if points and at < points[-1][0]:
            raise Invalid("invalid", shape)
        points.append([at, *(fraction(c, f"points[{n}] colour and opacity") for c in p[1:])])
    return points


async def on_display(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """Which parts show, how opaque, and the clipping: the presenter's for everyone, or
    the owner's while nobody presents; kept, so a reload (and a late joiner) sees it."""
    if room.presenter != person.id and not (person.visitor.owner and room.presenter is None):
        raise Invalid(
            "not_presenter",
            "only the presenter (or the model's owner while nobody presents) sets what shows.",
        )
    data = display_state(message)
    stored_id, at = await hub.store_event(room, person, "display", data)
    room.state.apply(stored_id, at, "display", person.visitor.name, data)
    item = {"id": stored_id, "author": person.visitor.name, "at": at, **data}
    event = (stored_id, at, "display", person.visitor.name, data)
    hub.broadcast(
        room, {"type": "display", "from": person.id, "item": item}, skip=person, event=event
    )


async def on_rename(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """A guest's new display name (an account's name is its account's): one ``rename``
    event, not a leave and a join."""
    if not person.visitor.guest:
        raise Invalid("forbidden", "your name is your account's; only guests choose theirs.")
    old = person.visitor.name
    new = guest_name(text(message.get("name"), "name", MAX_NAME * 4))
    if new == old:
        return
    person.visitor = dataclasses.replace(person.visitor, name=new)
    await hub.store_event(room, person, "rename", {"from": old, "to": new})
    hub.broadcast(room, {"type": "renamed", "participant": person.public()})


async def on_laser(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """Show the sender's laser point on the model to the others (None: laser off); not kept."""
    _check_model(room, message)
    at = message.get("point")
    at = None if at is None else room.on_model(point(at, "point"), "the laser point")
    frame = {"type": "laser", "from": person.id, "colour": person.colour, "point": at}
    hub.broadcast(room, frame, skip=person)


async def on_pin(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """Put a pin with an optional note at a point on the model; kept in the room's record."""
    _check_model(room, message)
    data = {
        "point": room.on_model(point(message.get("point"), "point"), "the pin"),
        "note": text(message.get("note"), "note", MAX_NOTE, required=False),
        "colour": person.colour,
        "by": person.visitor.key,
    }
    await _keep(hub, room, person, "pin", data)


async def on_measure(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """Measure between two points on the model (distance in mm, to 0.01); kept in the
    room's record."""
    _check_model(room, message)
    a = room.on_model(point(message.get("a"), "a"), "the first point")
    b = room.on_model(point(message.get("b"), "b"), "the second point")
    data = {"a": a, "b": b, "mm": round(math.dist(a, b), 2), "colour": person.colour}
    await _keep(hub, room, person, "measure", data | {"by": person.visitor.key})


async def on_chat(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """Post a chat message; kept in the room's record."""
    data = {"text": text(message.get("text"), "text", MAX_CHAT), "colour": person.colour}
    await _keep(hub, room, person, "chat", data)


async def _keep(hub: Hub, room: Room, person: Participant, kind: str, data: dict[str, Any]) -> None:
    """Store an event, fold it into the room and send it to everyone (the sender too:
    it learns the id)."""
    stored_id, at = await hub.store_event(room, person, kind, data)
    room.state.apply(stored_id, at, kind, person.visitor.name, data)
    item = {"id": stored_id, "author": person.visitor.name, "at": at, **data}
    item = public_item(room.model_id, item)
    event = (stored_id, at, kind, person.visitor.name, data)
    hub.broadcast(room, {"type": kind, "item": item}, event=event)


async def on_remove(hub: Hub, room: Room, person: Participant, message: dict[str, Any]) -> None:
    """``unpin`` / ``unmeasure``: by their author or the model's owner."""
    kind = message["type"]
    items = room.state.pins if kind == "unpin" else room.state.measurements
    target = event_id(message.get("id"), items, "pin" if kind == "unpin" else "measurement")
    if items[target].get("by") != person.visitor.key and not person.visitor.owner:
        raise Invalid("forbidden", "only its author or the model's owner may remove it.")
    stored_id, at = await hub.store_event(room, person, kind, {"id": target})
    room.state.apply(stored_id, at, kind, person.visitor.name, {"id": target})
    event = (stored_id, at, kind, person.visitor.name, {"id": target})
    hub.broadcast(room, {"type": kind, "id": target}, event=event)


HANDLERS: dict[str, Handler] = {
    "ping": on_ping,
    "presenter": on_presenter,
    "camera": on_camera,
    "laser": on_laser,
    "pin": on_pin,
    "unpin": on_remove,
    "measure": on_measure,
    "unmeasure": on_remove,
    "chat": on_chat,
    "display": on_display,
    "rename": on_rename,
}
