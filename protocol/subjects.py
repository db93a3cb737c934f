"""Where a room's messages go on NATS (docs/rooms.md): one place for the names.

- ``fw.ROOM.m.NAME``: NAME's media, one sealed bundle a message (protocol/bundle.py);
- ``fw.ROOM.c.TARGET.FROM``: a control message (a keyframe request) from FROM to TARGET;
- the JetStream KV bucket ``fw_ROOM``, key NAME: NAME's current snapshot, sealed.

Room and participant names are single NATS subject tokens (and KV keys): letters, digits,
``-`` and ``_``.
"""

from __future__ import annotations

import re

_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")
PREFIX = "fw"


def check_name(name: str, what: str) -> str:
    """``name`` if it can be a room's or participant's name; ValueError saying why not."""
    if not _NAME.fullmatch(name):
        raise ValueError(
            f"{what} name {name!r}: use 1-64 letters, digits, '-' or '_' (it is a NATS subject "
            "token)"
        )
    return name


def media(room: str, name: str = "*") -> str:
    return f"{PREFIX}.{room}.m.{name}"


def control(room: str, target: str, sender: str = "*") -> str:
    return f"{PREFIX}.{room}.c.{target}.{sender}"


def bucket(room: str) -> str:
    return f"{PREFIX}_{room}"


def parse(subject: str) -> tuple[str, str, str | None]:
    """(kind "m" or "c", the sender, the target of a control message) of a room's subject."""
    parts = subject.split(".")
    if len(parts) == 4 and parts[2] == "m":
        return "m", parts[3], None
    if len(parts) == 5 and parts[2] == "c":
        return "c", parts[4], parts[3]
    raise ValueError(f"not a room subject: {subject!r}")
