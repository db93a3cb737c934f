"""CURVE on real loopback sockets: only allowed receivers join, only the real sender is believed."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
import zmq
from transport_helpers import TIMEOUT_MS, Context, frame, join, keypairs, snapshot, wait_until
from zmq.utils.monitor import recv_monitor_message

from facewire.protocol.packets import KeyFrame, KeyframeRequest
from facewire.protocol.transport import ReceiverEndpoint, SenderEndpoint, TransportError

Keys = dict[str, tuple[Path, Path]]


@pytest.fixture
def keys(tmp_path: Path) -> Keys:
    """Keypairs of the sender, an allowed receiver (alice) and two strangers."""
    return keypairs(tmp_path, "sender", "alice", "mallory", "impostor")


@pytest.fixture
def sender(keys: Keys) -> Iterator[SenderEndpoint]:
    # Its own context: close() then really frees the ports (the impostor test binds them).
    s = SenderEndpoint(secret_key_file=keys["sender"][1], allowed_keys=[keys["alice"][0]])
    s.set_snapshot(snapshot())
    yield s
    s.close()


def receiver(sender: SenderEndpoint, context: Context, keys: Keys, name: str) -> ReceiverEndpoint:
    return ReceiverEndpoint(
        "127.0.0.1",
        *sender.ports,
        context=context,
        secret_key_file=keys[name][1],
        server_key_file=keys["sender"][0],
    )


def receive_frames(receiver: ReceiverEndpoint, count: int) -> list[int]:
    seqs: list[int] = []
    while len(seqs) < count:
        packet = receiver.recv(TIMEOUT_MS)
        assert packet is not None, f"lost frames after {len(seqs)}"
        if isinstance(packet, KeyFrame):
            seqs.append(packet.seq)
    return seqs


def test_allowed_receiver_joins_and_talks_back(
    sender: SenderEndpoint, context: Context, keys: Keys
) -> None:
    with receiver(sender, context, keys, "alice") as alice:
        assert join(sender, alice) == snapshot()
        for seq in range(20):
            sender.publish(frame(seq))
        assert receive_frames(alice, 20) == list(range(20))
        alice.request_keyframe(19)
        assert wait_until(lambda: bool(sender._inbox), 5, lambda: sender._read_router(100))
        assert sender.poll(0) == [KeyframeRequest(19)]


def test_receiver_with_unlisted_key_receives_nothing(
    sender: SenderEndpoint, context: Context, keys: Keys
) -> None:
    with (
        receiver(sender, context, keys, "alice") as alice,
        receiver(sender, context, keys, "mallory") as mallory,
    ):
        join(sender, alice)
        with pytest.raises(TransportError) as info:
            mallory.fetch_snapshot(timeout_ms=1000)
        assert "the sender refused this receiver's key" in str(info.value)
        for seq in range(10):
            sender.publish(frame(seq))
        assert receive_frames(alice, 10) == list(range(10))  # published, and delivered
        assert not mallory._sub.poll(0, zmq.POLLIN)
        assert sender.snapshots_served == 1  # alice's only
        assert mallory.snapshot is None and mallory.stats.received == 0


def curve_dealer(context: Context, sender: SenderEndpoint, keys: Keys, name: str | None):
    """A raw DEALER (CURVE client with ``name``'s keys, or plain) and its monitor socket."""
    from facewire.protocol.keys import load_keypair, load_public_key

    dealer = context.socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    if name is not None:
        pair = load_keypair(keys[name][1])
        dealer.curve_secretkey = pair.secret
        dealer.curve_publickey = pair.public
        dealer.curve_serverkey = load_public_key(keys["sender"][0])
    monitor = dealer.get_monitor_socket(
        zmq.EVENT_HANDSHAKE_SUCCEEDED
        | zmq.EVENT_HANDSHAKE_FAILED_AUTH
        | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
        | zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
    )
    monitor.setsockopt(zmq.LINGER, 0)
    dealer.connect(f"tcp://127.0.0.1:{sender.ports[1]}")
    return dealer, monitor


@pytest.mark.parametrize("name", ["mallory", None], ids=["unlisted-key", "plaintext"])
def test_stranger_cannot_inject_on_the_back_channel(
    sender: SenderEndpoint, context: Context, keys: Keys, name: str | None
) -> None:
    dealer, monitor = curve_dealer(context, sender, keys, name)
    try:
        for _ in range(10):
            dealer.send(bytes(KeyframeRequest(666)), zmq.NOBLOCK)
        assert monitor.poll(TIMEOUT_MS, zmq.POLLIN), "no handshake verdict"
        event = recv_monitor_message(monitor)["event"]
        # A plain client meets a CURVE server: the mechanisms differ, and the server hangs up;
        # the client reads that as a protocol error, or (the hang-up first) as a broken pipe.
        expected = (
            {zmq.EVENT_HANDSHAKE_FAILED_AUTH}
            if name
            else {zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL, zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL}
        )
        assert event in expected, zmq.Event(event)
        with receiver(sender, context, keys, "alice") as alice:
            join(sender, alice)
            alice.request_keyframe(1)
            got: list[object] = []
            assert wait_until(lambda: bool(got), 5, lambda: got.extend(sender.poll(100)))
            assert got == [KeyframeRequest(1)]
            assert sender.poll(0) == []
    finally:
        monitor.close(linger=0)
        dealer.close(linger=0)


def test_plaintext_receiver_gets_nothing_from_a_curve_sender(
    sender: SenderEndpoint, context: Context
) -> None:
    with ReceiverEndpoint("127.0.0.1", *sender.ports, context=context, plain=True) as plain:
        with pytest.raises(TransportError) as info:
            plain.fetch_snapshot(timeout_ms=1000)
        assert "handshake failed" in str(info.value)
        sender.publish(frame(1))
        assert plain.stats.received == 0 and not plain._sub.poll(0, zmq.POLLIN)
    assert sender.stats.received == 0 and sender.snapshots_served == 0


@pytest.mark.parametrize("impostor_keys", [True, False], ids=["other-key", "plaintext"])
def test_impostor_on_the_senders_ports_is_never_believed(
    sender: SenderEndpoint, context: Context, keys: Keys, impostor_keys: bool
) -> None:
    """Port takeover: the sender dies and another process binds its ports and publishes."""
    with receiver(sender, context, keys, "alice") as alice:
        join(sender, alice)
        ports = sender.ports
        sender.close()
        options: dict[str, object] = (
            {"secret_key_file": keys["impostor"][1], "allowed_keys": [keys["alice"][0]]}
            if impostor_keys
            else {"plain": True}
        )
        with SenderEndpoint(pub_port=ports[0], snapshot_port=ports[1], **options) as impostor:  # type: ignore[arg-type]
            impostor.set_snapshot(snapshot(session_id=666))
            got: list[object] = []

            def step() -> None:
                impostor.publish(frame(len(got) + 1000, session_id=7))
                impostor.poll(0)
                got.append(alice.recv(50))

            assert wait_until(lambda: alice.handshake_error is not None, 5, step)
            assert "handshake failed" in alice.handshake_error  # type: ignore[operator]
            assert not any(isinstance(p, KeyFrame) for p in got)
            with pytest.raises(TransportError):
                alice.fetch_snapshot(timeout_ms=500)
            assert impostor.snapshots_served == 0 and impostor.stats.received == 0


def test_mode_must_be_explicit(keys: Keys) -> None:
    with pytest.raises(TransportError) as info:
        SenderEndpoint()
    assert str(info.value) == (
        "sender: no CURVE keys (secret_key_file, allowed_keys); "
        "pass keys or plain=True for an unencrypted call"
    )
    with pytest.raises(TransportError, match="receiver: no CURVE keys"):
        ReceiverEndpoint("127.0.0.1", 1, 2)
    with pytest.raises(TransportError, match="plain=True and key files exclude each other"):
        ReceiverEndpoint("127.0.0.1", 1, 2, plain=True, server_key_file=keys["sender"][0])
    with pytest.raises(TransportError, match="CURVE needs both secret_key_file and allowed_keys"):
        SenderEndpoint(secret_key_file=keys["sender"][1])
    with pytest.raises(ValueError, match="has no secret-key line \\(that is a public key file\\)"):
        SenderEndpoint(secret_key_file=keys["sender"][0], allowed_keys=[keys["alice"][0]])
