"""A room participant's sealed stream without a relay: the real sender's loop
(sender/session.run_sender) publishing through :class:`~facewire.room_sender.RoomSender` into a
link that keeps what it is given, or hands it on as it comes, for a
:class:`~facewire.room_peer.RoomReceiver` to be fed message by message."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from facewire.protocol.clock import now_us
from facewire.protocol.media_path import DEFAULT_BUDGET_BPS
from facewire.protocol.sframe import RoomKey, Sealer, new_kid
from facewire.room_sender import RoomSender
from facewire.sender.audio import AudioSettings, frame_ms_for, sound_for, with_sound
from facewire.sender.capture import demo_clip_path
from facewire.sender.session import run_sender
from tests.call_helpers import start_sender


@dataclass
class KeptLink:
    """The part of RoomLink a RoomSender uses: publishes kept in order (and handed to
    ``deliver`` with their arrival time, when given), the snapshot kept."""

    deliver: Callable[[str, bytes, int], None] | None = None
    messages: list[tuple[str, bytes]] = field(default_factory=list)
    snapshot: bytes | None = None

    def publish(self, subject: str, data: bytes) -> None:
        self.messages.append((subject, data))
        if self.deliver is not None:
            self.deliver(subject, data, now_us())

    def put_snapshot(self, data: bytes) -> None:
        self.snapshot = data


def sealed_stream(
    key: RoomKey, name: str, frames: int, link: KeptLink | None = None, sound: bool = False
) -> KeptLink:
    """``name``'s first ``frames`` frames of the bundled clip (and its speech, with
    ``sound``), sent at the clip's pace as a room sends them (sealed bundles, the Bye last),
    and its sealed snapshot, into ``link`` (a new one that keeps them if None)."""
    encoder, snapshot, rest = start_sender(frames)
    link = link or KeptLink()
    sealer = Sealer(key.base_key(name), new_kid(name))
    endpoint = RoomSender(link, key, name, sealer, snapshot.fps, DEFAULT_BUDGET_BPS)  # type: ignore[arg-type]
    endpoint.set_snapshot(snapshot)
    sent = rest
    if sound:
        settings = AudioSettings(frame_ms=frame_ms_for(DEFAULT_BUDGET_BPS))
        speech = sound_for(demo_clip_path(), False, True, endpoint.publish, settings)
        assert speech is not None, "the bundled clip has its speech beside it"
        sent = with_sound(rest, speech, snapshot.fps)
    run_sender(endpoint, encoder, sent)  # type: ignore[arg-type]
    return link
