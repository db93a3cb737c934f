"""Restarts: a new sender on the same ports is noticed and rejoined; a new receiver joins."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from transport_helpers import TIMEOUT_MS, Context, frame, join, keypairs, rejoin, snapshot

from facewire.protocol.packets import Heartbeat, KeyFrame
from facewire.protocol.transport import (
    ReceiverEndpoint,
    RejoinNeeded,
    SenderEndpoint,
    TransportError,
)

Keys = dict[str, tuple[Path, Path]]


@pytest.fixture
def keys(tmp_path: Path) -> Keys:
    return keypairs(tmp_path, "sender", "alice", "bob")


def new_sender(keys: Keys, session_id: int, ports: tuple[int, int] = (0, 0)) -> SenderEndpoint:
    # Its own context: close() frees the ports at once for the next sender.
    sender = SenderEndpoint(
        pub_port=ports[0],
        snapshot_port=ports[1],
        secret_key_file=keys["sender"][1],
        allowed_keys=[keys["alice"][0], keys["bob"][0]],
    )
    sender.set_snapshot(snapshot(session_id=session_id))
    return sender


def new_receiver(sender: SenderEndpoint, context: Context, keys: Keys, name: str):
    return ReceiverEndpoint(
        "127.0.0.1",
        *sender.ports,
        context=context,
        secret_key_file=keys[name][1],
        server_key_file=keys["sender"][0],
    )


def test_restarted_sender_is_noticed_and_rejoined(context: Context, keys: Keys) -> None:
    first = new_sender(keys, session_id=1)
    ports = first.ports
    with new_receiver(first, context, keys, "alice") as alice:
        assert join(first, alice).session_id == 1
        first.publish(frame(0, session_id=1))
        assert isinstance(alice.recv(TIMEOUT_MS), (KeyFrame, Heartbeat))
        first.close()
        with new_sender(keys, session_id=2, ports=ports) as second:
            started = time.monotonic()
            with pytest.raises(RejoinNeeded, match="connection dropped and came back"):
                while time.monotonic() - started < 5:
                    second.publish(frame(1, session_id=2))  # what a restarted sender sends
                    second.poll(0)
                    packet = alice.recv(50)
                    if isinstance(packet, KeyFrame):  # queued before the restart, or a bug
                        assert packet.session_id == 1, "a new session's frame was taken"
            assert time.monotonic() - started < 5
            with pytest.raises(RejoinNeeded):  # until the caller rejoins
                alice.recv(0)
            assert rejoin(second, alice).session_id == 2
            assert alice.session_id == 2 and alice.peer_alive
            second.publish(frame(7, session_id=2))
            packet = alice.recv(TIMEOUT_MS)
            while isinstance(packet, Heartbeat):
                packet = alice.recv(TIMEOUT_MS)
            assert packet == frame(7, session_id=2)


def test_update_from_another_session_asks_for_a_rejoin(context: Context, keys: Keys) -> None:
    with (
        new_sender(keys, session_id=1) as sender,
        new_receiver(sender, context, keys, "alice") as alice,
    ):
        join(sender, alice)
        sender.publish(Heartbeat(9, 0, 0))  # a session the snapshot does not know
        with pytest.raises(RejoinNeeded, match=r"session changed \(1 -> 9\)"):
            while alice.recv(TIMEOUT_MS) is not None:
                pass
        assert rejoin(sender, alice).session_id == 1  # same sender: the rejoin is harmless


def test_new_receiver_joins_after_the_old_one_left(context: Context, keys: Keys) -> None:
    with new_sender(keys, session_id=3) as sender:
        with new_receiver(sender, context, keys, "alice") as alice:
            join(sender, alice)
            for seq in range(5):
                sender.publish(frame(seq, session_id=3))
        started = time.monotonic()
        with new_receiver(sender, context, keys, "bob") as bob:
            assert rejoin(sender, bob).session_id == 3
            assert time.monotonic() - started < 5
            sender.publish(frame(5, session_id=3))
            packet = bob.recv(TIMEOUT_MS)
            while isinstance(packet, Heartbeat):
                packet = bob.recv(TIMEOUT_MS)
            assert packet == frame(5, session_id=3)
        assert sender.snapshots_served == 2


def test_rejoin_fails_cleanly_when_the_sender_is_gone(context: Context, keys: Keys) -> None:
    sender = new_sender(keys, session_id=1)
    with new_receiver(sender, context, keys, "alice") as alice:
        join(sender, alice)
        sender.close()
        with pytest.raises(TransportError, match="no published packet"):
            alice.fetch_snapshot(timeout_ms=300)
        assert alice.snapshot is None and alice.session_id is None
