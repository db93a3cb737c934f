"""Reversed roles: the receiver binds and the sender connects, on real loopback sockets.

Everything above the sockets must work as in the usual direction: the Clone handshake, the back
channel, CURVE (the sender stays the server and admits only its allowed keys), and noticing a
restarted sender.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest
import zmq
from transport_helpers import TIMEOUT_MS, Context, frame, join, keypairs, snapshot, wait_until

from facewire.protocol.packets import Heartbeat, KeyFrame, KeyframeRequest
from facewire.protocol.transport import (
    ReceiverEndpoint,
    RejoinNeeded,
    SenderEndpoint,
    TransportError,
)

Keys = dict[str, tuple[Path, Path]]


@pytest.fixture
def keys(tmp_path: Path) -> Keys:
    return keypairs(tmp_path, "sender", "alice", "mallory", "impostor")


def bound_receiver(context: Context, keys: Keys | None, name: str = "alice") -> ReceiverEndpoint:
    options: dict[str, object] = (
        {"plain": True}
        if keys is None
        else {"secret_key_file": keys[name][1], "server_key_file": keys["sender"][0]}
    )
    return ReceiverEndpoint("127.0.0.1", 0, 0, context=context, bind=True, **options)  # type: ignore[arg-type]


def connecting_sender(
    receiver: ReceiverEndpoint, keys: Keys | None, context: Context | None = None, session: int = 7
) -> SenderEndpoint:
    options: dict[str, object] = (
        {"plain": True}
        if keys is None
        else {"secret_key_file": keys["sender"][1], "allowed_keys": [keys["alice"][0]]}
    )
    pub, snap = receiver.ports
    sender = SenderEndpoint(
        "127.0.0.1",
        pub,
        snap,
        context=context,
        connect=True,
        **options,  # type: ignore[arg-type]
    )
    sender.set_snapshot(snapshot(session_id=session))
    return sender


def frames_received(receiver: ReceiverEndpoint, count: int) -> list[int]:
    seqs: list[int] = []
    while len(seqs) < count:
        packet = receiver.recv(TIMEOUT_MS)
        assert packet is not None, f"lost frames after {len(seqs)}"
        if isinstance(packet, KeyFrame):
            seqs.append(packet.seq)
    return seqs


@pytest.mark.parametrize("curve", [False, True], ids=["plain", "curve"])
def test_sender_connects_to_a_bound_receiver(context: Context, keys: Keys, curve: bool) -> None:
    used = keys if curve else None
    with bound_receiver(context, used) as receiver:
        pub, snap = receiver.ports
        assert 0 < pub != snap > 0  # port 0 picked free ports
        with connecting_sender(receiver, used, context) as sender:
            assert sender.ports == (pub, snap)
            assert join(sender, receiver) == snapshot()
            for seq in range(40):
                sender.publish(frame(seq))
            assert frames_received(receiver, 40) == list(range(40))
            receiver.request_keyframe(39)
            got: list[object] = []
            assert wait_until(lambda: bool(got), 5, lambda: got.extend(sender.poll(100)))
            # On DEALER, and a copy in a datagram: the media path opened with the join.
            assert got in ([KeyframeRequest(39)], [KeyframeRequest(39)] * 2)


def test_connecting_sender_admits_only_its_allowed_keys(context: Context, keys: Keys) -> None:
    with bound_receiver(context, keys, "mallory") as mallory:
        with connecting_sender(mallory, keys, context) as sender:
            with pytest.raises(TransportError) as info:
                mallory.fetch_snapshot(timeout_ms=1000)
            assert "the sender refused this receiver's key" in str(info.value)
            sender.publish(frame(1))
            assert not mallory._sub.poll(200, zmq.POLLIN)
            assert sender.snapshots_served == 0 and mallory.stats.received == 0


def test_bound_receiver_does_not_believe_a_sender_with_another_key(
    context: Context, keys: Keys
) -> None:
    with bound_receiver(context, keys) as alice:
        pub, snap = alice.ports
        with SenderEndpoint(
            "127.0.0.1",
            pub,
            snap,
            context=context,
            connect=True,
            secret_key_file=keys["impostor"][1],
            allowed_keys=[keys["alice"][0]],
        ) as impostor:
            impostor.set_snapshot(snapshot(session_id=666))
            with pytest.raises(TransportError, match="handshake failed"):
                alice.fetch_snapshot(timeout_ms=1000)
            assert impostor.snapshots_served == 0 and alice.stats.received == 0


def test_restarted_connecting_sender_is_noticed_and_rejoined(context: Context, keys: Keys) -> None:
    with bound_receiver(context, keys) as alice:
        # Own contexts: closing a sender really drops its connections.
        first = connecting_sender(alice, keys, session=1)
        assert join(first, alice).session_id == 1
        first.close()
        with connecting_sender(alice, keys, session=2) as second:
            started = time.monotonic()
            with pytest.raises(RejoinNeeded):
                while time.monotonic() - started < 5:
                    second.publish(frame(1, session_id=2))
                    second.poll(0)
                    packet = alice.recv(50)
                    if isinstance(packet, KeyFrame):
                        assert packet.session_id == 1, "a new session's frame was taken"
            assert join(second, alice).session_id == 2
            second.publish(frame(9, session_id=2))
            packet = alice.recv(TIMEOUT_MS)
            while isinstance(packet, Heartbeat):
                packet = alice.recv(TIMEOUT_MS)
            assert packet == frame(9, session_id=2)


def test_bind_and_connect_errors_are_one_line(context: Context) -> None:
    with bound_receiver(context, None) as taken:
        pub, snap = taken.ports
        with pytest.raises(TransportError) as info:
            ReceiverEndpoint("127.0.0.1", pub, 0, context=context, bind=True, plain=True)
        assert str(info.value).startswith(f"receiver: cannot bind on 127.0.0.1 ports ({pub}, 0)")
        assert "Address already in use" in str(info.value)
        with pytest.raises(TransportError, match=r"sender: cannot bind on 127.0.0.1 ports"):
            SenderEndpoint("127.0.0.1", 0, snap, context=context, plain=True)
    with pytest.raises(TransportError, match=r"cannot connect to port 0 \(expected 1..65535\)"):
        SenderEndpoint("127.0.0.1", 0, 0, context=context, connect=True, plain=True)
    with pytest.raises(TransportError, match="receiver: cannot connect to port 70000"):
        ReceiverEndpoint("127.0.0.1", 70000, 1, context=context, plain=True)
