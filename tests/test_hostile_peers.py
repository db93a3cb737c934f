"""Strangers on a bound receiver's ports: the live session is kept (docs/protocol.md 3.8).

A receiver that binds (``--bind``) takes connections from whoever reaches its ports; in
``--plain`` mode nothing proves who they are. Each test joins a real sender over loopback,
then a stranger (real ZeroMQ sockets, in this process) connects to the receiver's SUB or
DEALER port and does what a peer written from the protocol's text alone might: connect and
leave, publish another session's packets, a Bye, random bytes, huge messages. The receiver
keeps its session, counts what it ignored, and takes the sender's next frames.
"""

from __future__ import annotations

import os
import random
from collections.abc import Iterator

import pytest
import zmq
from transport_helpers import SESSION, TIMEOUT_MS, Context, frame, join, rss_bytes, wait_until

from facewire.protocol.constants import UINT32_MAX
from facewire.protocol.packets import AudioFrame, Bye, Heartbeat, KeyFrame, Packet
from facewire.protocol.transport import ReceiverEndpoint, SenderEndpoint

WAIT_S = TIMEOUT_MS / 1000


@pytest.fixture
def call(context: Context) -> Iterator[tuple[SenderEndpoint, ReceiverEndpoint]]:
    """A receiver bound in plain mode, its sender connected and joined, the session's
    connection known (the receiver took the sender's first packet)."""
    from transport_helpers import snapshot

    with ReceiverEndpoint("127.0.0.1", 0, 0, context=context, plain=True, bind=True) as receiver:
        with SenderEndpoint(
            "127.0.0.1", *receiver.ports, context=context, plain=True, connect=True, udp=False
        ) as sender:
            sender.set_snapshot(snapshot())
            join(sender, receiver)
            assert next_update(sender, receiver, frame(1)) == frame(1)
            yield sender, receiver


def next_update(sender: SenderEndpoint, receiver: ReceiverEndpoint, packet: Packet) -> Packet:
    """Publish ``packet`` and return the receiver's next update other than a Heartbeat."""
    sender.publish(packet)
    got = receiver.recv(TIMEOUT_MS)
    while isinstance(got, Heartbeat):
        got = receiver.recv(TIMEOUT_MS)
    assert got is not None, f"{packet} never came"
    return got


@pytest.fixture
def strangers(context: Context) -> Iterator[list[zmq.Socket[bytes]]]:
    """Sockets of the test's strangers, closed at its end whatever happened."""
    made: list[zmq.Socket[bytes]] = []
    yield made
    for sock in made:
        sock.close(linger=0)


def stranger_pub(
    context: Context, receiver: ReceiverEndpoint, made: list[zmq.Socket[bytes]]
) -> zmq.Socket[bytes]:
    """A PUB connected to the receiver's SUB, once what it sends gets there: until then (its
    PUB has not heard the receiver's subscription) it repeats another session's Heartbeat,
    until the receiver has ignored one."""
    sock = context.socket(zmq.PUB)
    made.append(sock)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(f"tcp://127.0.0.1:{receiver.ports[0]}")
    before = receiver.stats.ignored_sessions

    def step() -> None:
        sock.send(bytes(Heartbeat(98, 0, 0)))
        receiver.recv(20)

    assert wait_until(lambda: receiver.stats.ignored_sessions > before, WAIT_S, step)
    return sock


def drain(receiver: ReceiverEndpoint, more: int) -> list[Packet]:
    """recv() until ``stats.ignored_sessions`` has grown by ``more``; what it returned."""
    until = receiver.stats.ignored_sessions + more
    taken: list[Packet] = []

    def step() -> None:
        packet = receiver.recv(50)
        if packet is not None and not isinstance(packet, Heartbeat):
            taken.append(packet)

    assert wait_until(lambda: receiver.stats.ignored_sessions >= until, WAIT_S, step), (
        receiver.stats
    )
    return taken


def test_strangers_that_connect_and_leave_force_no_rejoin(
    context: Context,
    call: tuple[SenderEndpoint, ReceiverEndpoint],
    strangers: list[zmq.Socket[bytes]],
) -> None:
    """A port scan, or 16 peers that connect and leave, cost the session nothing (each
    used to make the receiver rejoin)."""
    sender, receiver = call
    for _ in range(16):
        stranger_pub(context, receiver, strangers).close(linger=0)
        receiver.recv(0)  # raises RejoinNeeded if the stranger's leaving was taken for ours
    for seq in range(2, 6):
        assert next_update(sender, receiver, frame(seq)) == frame(seq)
    assert receiver.session_id == SESSION and receiver.peer_alive


def test_a_second_sender_neither_switches_nor_ends_the_session(
    context: Context,
    call: tuple[SenderEndpoint, ReceiverEndpoint],
    strangers: list[zmq.Socket[bytes]],
) -> None:
    sender, receiver = call
    stranger = stranger_pub(context, receiver, strangers)
    hostile: list[Packet] = [
        Heartbeat(99, 0, 0),  # another session's heartbeat: was a rejoin
        frame(40, session_id=99),
        Bye(2),  # a forged Bye: ended the session
        frame(41),  # a forged frame of this very session, by another connection
        AudioFrame(3, 2**62, b"\xf8\xff\xfe"),  # an hour (and more) ahead
    ]
    for packet in hostile:
        stranger.send(bytes(packet))
    ignored = receiver.stats.ignored_sessions
    assert drain(receiver, len(hostile)) == []
    assert receiver.stats.ignored_sessions - ignored >= len(hostile)
    assert receiver.peer_alive and receiver.session_id == SESSION
    assert next_update(sender, receiver, frame(2)) == frame(2)
    stranger.close(linger=0)


def test_a_bye_beyond_any_frame_sent_is_refused(
    call: tuple[SenderEndpoint, ReceiverEndpoint],
) -> None:
    """A Bye at frame 2^32 - 1 (bytes 27 91 ce ff ff ff ff) made the receiver hold 300
    frames and end the session; the sender's own Bye still ends it."""
    sender, receiver = call
    assert bytes(Bye(UINT32_MAX)) == bytes.fromhex("2791ceffffffff")
    sender.publish(Bye(UINT32_MAX))
    assert next_update(sender, receiver, frame(2)) == frame(2)
    assert receiver.stats.malformed == 1 and receiver.peer_alive
    assert next_update(sender, receiver, Bye(3)) == Bye(3)
    assert not receiver.peer_alive


def test_random_bursts_from_a_stranger_are_dropped(
    context: Context,
    call: tuple[SenderEndpoint, ReceiverEndpoint],
    strangers: list[zmq.Socket[bytes]],
) -> None:
    sender, receiver = call
    stranger = stranger_pub(context, receiver, strangers)
    rng = random.Random(24)
    valid = [bytes(Heartbeat(rng.randrange(1 << 32), 0, 0)) for _ in range(100)]
    for data in valid:
        stranger.send(data)
    for _ in range(1000):
        stranger.send(bytes([0x20 | rng.randrange(16)]) + rng.randbytes(rng.randrange(40)))
    drain(receiver, len(valid))
    assert next_update(sender, receiver, frame(2)) == frame(2)
    assert receiver.session_id == SESSION and receiver.peer_alive
    stranger.close(linger=0)


def test_a_stranger_on_the_bound_dealer_is_not_heard(
    context: Context,
    call: tuple[SenderEndpoint, ReceiverEndpoint],
    strangers: list[zmq.Socket[bytes]],
) -> None:
    """Frame copies (the second path) come only by the connection that brought the snapshot;
    a stranger's are not even decoded, a 16 MiB one neither."""
    sender, receiver = call
    stranger = context.socket(zmq.DEALER)
    strangers.append(stranger)
    stranger.setsockopt(zmq.LINGER, 0)
    stranger.connect(f"tcp://127.0.0.1:{receiver.ports[1]}")
    stranger.send(bytes(frame(2)))
    stranger.send(bytes(frame(3, session_id=99)))
    stranger.send(b"\x22" * (16 * 1024 * 1024 - 1))
    assert drain(receiver, 3) == []
    assert next_update(sender, receiver, frame(2)) == frame(2)
    stranger.close(linger=0)


def test_huge_messages_on_the_update_port_cost_no_memory(
    context: Context,
    call: tuple[SenderEndpoint, ReceiverEndpoint],
    strangers: list[zmq.Socket[bytes]],
) -> None:
    """A message beyond MAX_UPDATE_BYTES ends the stranger's connection: 64 queued messages
    of just under 16 MiB once took 1 GiB."""
    sender, receiver = call
    before = rss_bytes()
    big = os.urandom(8 * 1024 * 1024)
    for _ in range(8):
        stranger = stranger_pub(context, receiver, strangers)
        monitor = stranger.get_monitor_socket(zmq.EVENT_DISCONNECTED)
        strangers.append(monitor)
        stranger.send(big, copy=False)
        assert monitor.poll(TIMEOUT_MS), "the receiver kept a connection sending 8 MiB"
        stranger.disable_monitor()
        monitor.close(linger=0)
        stranger.close(linger=0)
    assert next_update(sender, receiver, frame(2)) == frame(2)
    assert rss_bytes() - before < 32 * 1024 * 1024


def test_the_senders_own_new_session_still_asks_for_a_rejoin(
    call: tuple[SenderEndpoint, ReceiverEndpoint],
) -> None:
    """The session's own connection naming another session is the sender starting anew."""
    from facewire.protocol.transport import RejoinNeeded

    sender, receiver = call
    sender.publish(KeyFrame(9, 12, 50, 0, b"x"))
    with pytest.raises(RejoinNeeded, match=r"session changed \(7 -> 12\)"):
        for _ in range(100):
            receiver.recv(50)


def test_refusals_are_logged_at_most_once_a_second(caplog: pytest.LogCaptureFixture) -> None:
    from facewire.protocol.hostile import Refusals

    now = [100.0]
    refusals = Refusals(lambda: now[0])
    with caplog.at_level("WARNING", logger="facewire.protocol.hostile"):
        for _ in range(1000):  # a flood within one second: one line
            refusals.refuse("ignored a Heartbeat")
            now[0] += 0.0009
        now[0] += 0.2
        refusals.refuse("ignored a Bye")
    assert [r.getMessage() for r in caplog.records] == [
        "ignored a Heartbeat",
        "ignored a Bye (and 999 more refused since the last line)",
    ]
