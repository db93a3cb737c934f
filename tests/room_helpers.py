"""A room participant's sealed stream without a relay: the real sender's loop
(sender/session.run_sender) publishing through :class:`~facewire.room_sender.RoomSender` into a
link that keeps what it is given, for a :class:`~facewire.room_peer.RoomReceiver` to be fed
message by message."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from facewire.protocol.sframe import RoomKey, Sealer, new_kid
from facewire.room_sender import RoomSender
from facewire.sender.session import run_sender
from tests.call_helpers import start_sender


@dataclass
class KeptLink:
    """The part of RoomLink a RoomSender uses: publishes kept in order, the snapshot kept."""

    messages: list[tuple[str, bytes]] = field(default_factory=list)
    snapshot: bytes | None = None

    def publish(self, subject: str, data: bytes) -> None:
        self.messages.append((subject, data))

    def put_snapshot(self, data: bytes) -> None:
        self.snapshot = data


def sealed_stream(key: RoomKey, name: str, frames: int, **sender: Any) -> KeptLink:
    """``name``'s first ``frames`` frames of the bundled clip, sent at the clip's pace as
    a room sends them (sealed bundles, the Bye last), and its sealed snapshot."""
    encoder, snapshot, rest = start_sender(frames)
    link = KeptLink()
    sealer = Sealer(key.base_key(name), new_kid(name))
    endpoint = RoomSender(link, key, name, sealer, snapshot.fps, 2000.0, **sender)  # type: ignore[arg-type]
    endpoint.set_snapshot(snapshot)
    run_sender(endpoint, encoder, rest)  # type: ignore[arg-type]
    return link
