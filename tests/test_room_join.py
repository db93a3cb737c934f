"""A newcomer to a room is joined off the receiving loop: while its snapshot is read and its
decoder built, the others' pictures go on, and its own messages wait for it."""

from __future__ import annotations

import threading
import time

import pytest

from facewire.protocol.sframe import RoomKey, Sealer, new_kid
from facewire.room_peer import RoomReceiver
from tests.room_helpers import sealed_stream

pytest.importorskip("cryptography")


def _run_until(receiver: RoomReceiver, done: object, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not done():  # type: ignore[operator]
        assert time.monotonic() < deadline, "timed out"
        receiver.run_once(0.05)


def test_the_others_go_on_while_a_newcomer_is_joined() -> None:
    key = RoomKey.generate("standup")
    alice = sealed_stream(key, "alice", 30)
    bob = sealed_stream(key, "bob", 30)
    # Bob's snapshot is slow to come (a loaded relay, a cluster electing the bucket's leader:
    # building his decoder takes as long on a loaded machine).
    bob_read = threading.Event()
    snapshots = {"alice": alice.snapshot, "bob": bob.snapshot}

    def get_snapshot(name: str) -> bytes | None:
        if name == "bob":
            assert bob_read.wait(30)
        return snapshots[name]

    said: list[str] = []
    receiver = RoomReceiver(
        key, "carol", get_snapshot=get_snapshot, publish=lambda subject, data: None,
        sealer=Sealer(key.base_key("carol"), new_kid("carol")), notify=said.append,
    )  # fmt: skip
    try:
        half = len(alice.messages) // 2
        for message in alice.messages[:half]:
            receiver.deliver(*message, 0)
        _run_until(receiver, lambda: "alice" in receiver.peers and receiver.inbox.empty())
        assert receiver.figures["alice"].frames > 0
        before = receiver.figures["alice"].frames
        receiver.deliver(*bob.messages[0], 0)  # bob comes: his snapshot is read
        for message in alice.messages[half:-1]:  # alice's stream goes on, all but her Bye
            receiver.deliver(*message, 0)
        _run_until(receiver, lambda: receiver.inbox.empty() and "bob" in receiver.joining)
        # Alice's pictures were decoded while bob was still being joined.
        assert receiver.figures["alice"].frames > before
        assert "bob" not in receiver.peers and not receiver.figures["bob"].frames
        for message in bob.messages[1:]:  # his stream waits for him
            receiver.deliver(*message, 0)
        bob_read.set()
        _run_until(receiver, lambda: receiver.figures["bob"].left == "said bye")
        # Everything he sent meanwhile was decoded once he was ready, to his Bye.
        assert receiver.figures["bob"].frames > 0
        assert receiver.figures["bob"].sessions == 1
        assert "bob joined: 640x480 at 30 fps" in said
    finally:
        bob_read.set()
        receiver.close()
