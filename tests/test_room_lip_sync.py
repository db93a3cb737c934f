"""A room's gallery shows each face with its voice: a picture is held until its sound is heard
(its capture time plus its peer's sound delay), not drawn as soon as it is decoded."""

from __future__ import annotations

import statistics
import threading
import time

from facewire.protocol.clock import now_us
from facewire.protocol.sframe import RoomKey, Sealer, new_kid
from facewire.room_gallery import GALLERY_FPS, Gallery
from facewire.room_peer import RoomReceiver
from facewire.room_sound import RoomSound
from tests.room_helpers import KeptLink, sealed_stream

#: Sound delays move by a step of the sound's (20 ms) between a picture's hold and its draw.
SLACK_MS = 20.0


def test_the_gallery_holds_each_face_until_its_voice_is_heard() -> None:
    key = RoomKey.generate("standup")
    said: list[str] = []
    # (when drawn µs, alice's picture's capture µs, her sound's delay then µs)
    drawn: list[tuple[int, int, int]] = []

    def sink(frame: object, report: object) -> None:
        peer = receiver.peers.get("alice")
        delay = peer.audio.delay_us() if peer is not None and peer.audio is not None else None
        if "alice" in gallery.captured and delay is not None:
            drawn.append((now_us(), gallery.captured["alice"], delay))

    gallery = Gallery(sink)
    sound = RoomSound(said.append, device=False)
    link = KeptLink()
    receiver = RoomReceiver(
        key, "carol", get_snapshot=lambda name: link.snapshot, publish=lambda *_: None,
        sealer=Sealer(key.base_key("carol"), new_kid("carol")), notify=said.append,
        gallery=gallery, sound=sound,
    )  # fmt: skip
    link.deliver = receiver.deliver  # alice's bundles come to carol as they are sent
    alice = threading.Thread(target=sealed_stream, args=(key, "alice", 150, link, True))
    try:
        alice.start()
        deadline = time.monotonic() + 60
        while receiver.figures.get("alice") is None or receiver.figures["alice"].left is None:
            assert time.monotonic() < deadline, said
            receiver.run_once(0.1)
    finally:
        alice.join()
        receiver.close()
        sound.close()
    assert receiver.figures["alice"].audio_packets > 0
    # Each of her pictures once, from the second after her sound began (its first pictures
    # came before any sound, and were shown at once).
    first: dict[int, tuple[int, int]] = {}
    for shown, captured, delay in drawn:
        first.setdefault(captured, (shown, delay))
    began = min(first) + 1_000_000
    offsets_ms = [
        ((shown - captured) - delay) / 1000 for captured, (shown, delay) in first.items()
        if captured > began
    ]  # fmt: skip
    assert len(offsets_ms) > 30
    print(
        f"alice's pictures on screen after her voice: median {statistics.median(offsets_ms):.0f}"
        f" ms, {min(offsets_ms):.0f} to {max(offsets_ms):.0f} ms ({len(offsets_ms)} pictures)"
    )
    # Never before its voice: drawn when decoded, a picture came 50-100 ms ahead of it (the
    # sound's jitter buffer holds 140 ms at least), ...
    assert min(offsets_ms) > -SLACK_MS, sorted(offsets_ms)[:5]
    # ... and within a frame of the gallery's after it.
    assert statistics.median(offsets_ms) < 1000 / GALLERY_FPS + SLACK_MS, offsets_ms
