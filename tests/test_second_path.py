"""The second path: frame copies over ROUTER/DEALER for a receiver that reports late frames.

It belongs to the media's TCP fallback (a datagram waits behind no retransmission), so these
endpoints have no UDP media path. Real ZeroMQ sockets on loopback. Where a test needs the
copies to come in an order loopback would not give by itself, the sender is a hand-made PUB
and ROUTER pair that follows the joining handshake of docs/protocol.md 3.2.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest
import zmq
from transport_helpers import SESSION, TIMEOUT_MS, Context, frame, join, snapshot

from facewire.protocol import transport
from facewire.protocol.constants import LATE_FRAME_MS, LATE_FRAMES
from facewire.protocol.packets import (
    DeltaFrame,
    Heartbeat,
    KeyFrame,
    KeyframeRequest,
    ReceiverStats,
    SnapshotRequest,
    decode,
)
from facewire.protocol.transport import ReceiverEndpoint, SenderEndpoint
from facewire.receiver.lateness import LateFrames


@pytest.fixture
def sender(context: Context) -> Iterator[SenderEndpoint]:
    s = SenderEndpoint(context=context, plain=True, udp=False)
    s.set_snapshot(snapshot(seq=0))
    yield s
    s.close()


@pytest.fixture
def receiver(sender: SenderEndpoint, context: Context) -> Iterator[ReceiverEndpoint]:
    pub, snap = sender.ports
    r = ReceiverEndpoint("127.0.0.1", pub, snap, context=context, plain=True, udp=False)
    join(sender, r)
    yield r
    r.close()


def open_second_path(sender: SenderEndpoint, receiver: ReceiverEndpoint) -> None:
    receiver.note_late_frame()
    deadline = time.monotonic() + TIMEOUT_MS / 1000
    while sender.spare_peers == 0:
        assert time.monotonic() < deadline, "the late-frames report never opened the second path"
        sender.poll(10)


def sent_one_at_a_time(
    sender: SenderEndpoint, receiver: ReceiverEndpoint, packets: list[KeyFrame]
) -> list[KeyFrame]:
    """Publish each packet and read until the receiver has passed on as many frames, as a call
    sends them (the queues are small); what it passed on."""
    got: list[KeyFrame] = []
    for count, packet in enumerate(packets, 1):
        sender.publish(packet)
        while len(got) < count:
            received = receiver.recv(TIMEOUT_MS)
            assert received is not None, f"lost frames after {len(got)}"
            if isinstance(received, KeyFrame):
                got.append(received)
    return got


def frames_received(receiver: ReceiverEndpoint, until_copies: int) -> list[KeyFrame]:
    """Everything the receiver passes on until ``until_copies`` second copies were dropped."""
    got: list[KeyFrame] = []
    deadline = time.monotonic() + TIMEOUT_MS / 1000
    while receiver.stats.copies < until_copies:
        assert time.monotonic() < deadline, f"{receiver.stats.copies} copies of {until_copies}"
        packet = receiver.recv(50)
        if isinstance(packet, KeyFrame):
            got.append(packet)
    while (packet := receiver.recv(50)) is not None:  # nothing more comes
        if isinstance(packet, KeyFrame):
            got.append(packet)
    return got


def test_a_frame_delay_is_judged_against_the_fastest_recent_one() -> None:
    late = LateFrames(late_ms=50, window_s=10)
    offset = 5_000_000_000  # the ends' clocks differ by 5000 s: only differences count
    t = 0
    for i in range(300):  # 40 ms +- 10 ms of network delay: none late
        t += 33_333
        assert not late.late(t + offset + 40_000 + (i * 7919) % 20_000 - 10_000, t)
    t += 33_333
    assert late.late(t + offset + 130_000, t)  # waited for a retransmission
    t += 33_333
    assert not late.late(t + offset + 45_000, t)
    # The clocks drift 100 ms apart over 60 s: the window follows, no frame is late.
    drift = LateFrames(late_ms=50, window_s=10)
    for i in range(1800):
        t = i * 33_333
        assert not drift.late(t + offset + 40_000 + t // 600, t)


def test_a_frame_is_late_past_50_ms_as_the_protocol_says() -> None:
    """The threshold real sessions use (LateFrames()'s default; docs/protocol.md 3.6): 45 ms
    slower than the fastest recent frame is not late, 55 ms is. (A default of 5 ms sent about
    three times more second-path copies, and nothing failed.)"""
    for slower_ms, late in ((45, False), (55, True)):
        judge = LateFrames()
        assert not judge.late(1_040_000, 1_000_000)
        assert judge.late(1_073_333 + slower_ms * 1000, 1_033_333) is late, slower_ms


def test_a_receiver_that_reports_late_frames_gets_each_frame_once(
    sender: SenderEndpoint, receiver: ReceiverEndpoint
) -> None:
    assert sender.spare_peers == 0
    open_second_path(sender, receiver)
    packets = [frame(seq) for seq in range(1, 101)]
    got = sent_one_at_a_time(sender, receiver, packets)
    got += frames_received(receiver, until_copies=100)
    assert got == packets  # each once, in order, whichever path brought it
    assert receiver.stats.malformed == 0
    assert sender.bytes_sent["spare"] == sender.bytes_sent["geometry"]
    assert receiver.bytes_received["spare"] == sender.bytes_sent["spare"]
    assert receiver.stats.late_frames == 1


def test_no_copies_without_a_report_and_none_after_the_hold(
    sender: SenderEndpoint, receiver: ReceiverEndpoint, monkeypatch: pytest.MonkeyPatch
) -> None:
    sender.publish(frame(1))
    assert frames_received(receiver, until_copies=0) == [frame(1)]
    assert sender.bytes_sent["spare"] == 0 and receiver.stats.copies == 0
    monkeypatch.setattr(transport, "SPARE_PATH_HOLD_S", 0.3)
    open_second_path(sender, receiver)
    sender.publish(frame(2))
    assert frames_received(receiver, until_copies=1) == [frame(2)]
    time.sleep(0.4)
    sender.publish(frame(3))
    assert frames_received(receiver, until_copies=1) == [frame(3)]
    assert sender.spare_peers == 0 and receiver.stats.copies == 1


def test_a_peer_that_has_not_joined_gets_no_copies(
    sender: SenderEndpoint, context: Context
) -> None:
    dealer = context.socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    dealer.connect(f"tcp://127.0.0.1:{sender.ports[1]}")
    try:
        dealer.send(bytes(ReceiverStats({LATE_FRAMES: 5.0})))
        deadline = time.monotonic() + TIMEOUT_MS / 1000
        while not sender.poll(10):
            assert time.monotonic() < deadline
        assert sender.spare_peers == 0
    finally:
        dealer.close()


def next_update(receiver: ReceiverEndpoint, timeout_ms: int) -> object:
    """The next update that is not a Heartbeat (probe answers), or None."""
    while isinstance(packet := receiver.recv(timeout_ms), Heartbeat):
        pass
    return packet


class HandMadeSender:
    """A PUB and a ROUTER that join one receiver (3.2), then send on either path at will."""

    def __init__(self, context: Context) -> None:
        self.pub = context.socket(zmq.PUB)
        self.router = context.socket(zmq.ROUTER)
        for sock in (self.pub, self.router):
            sock.setsockopt(zmq.LINGER, 0)
        self.ports = (
            self.pub.bind_to_random_port("tcp://127.0.0.1"),
            self.router.bind_to_random_port("tcp://127.0.0.1"),
        )
        self.identity = b""
        self.received: list[object] = []

    def serve_join(self) -> None:
        deadline = time.monotonic() + TIMEOUT_MS / 1000
        while not self.identity and time.monotonic() < deadline:
            if not self.router.poll(50):
                continue
            identity, data = self.router.recv_multipart()
            packet = decode(data)
            if isinstance(packet, Heartbeat):
                self.pub.send(bytes(Heartbeat(SESSION, 0, 0)))
            elif isinstance(packet, SnapshotRequest):
                self.router.send_multipart([identity, bytes(snapshot(seq=0))])
                self.identity = identity

    def by_pub(self, packet: KeyFrame | DeltaFrame) -> None:
        self.pub.send(bytes(packet))

    def by_router(self, packet: object) -> None:
        self.router.send_multipart([self.identity, bytes(packet)])  # type: ignore[call-overload]

    def close(self) -> None:
        self.pub.close()
        self.router.close()


def test_the_first_copy_is_passed_on_and_a_late_second_one_counts(context: Context) -> None:
    hand = HandMadeSender(context)
    server = threading.Thread(target=hand.serve_join)
    server.start()
    receiver = ReceiverEndpoint("127.0.0.1", *hand.ports, context=context, plain=True)
    try:
        receiver.fetch_snapshot(TIMEOUT_MS)
        server.join()
        # The second path brings frame 1 first; the PUB's copy comes late (a retransmission).
        hand.by_router(frame(1))
        assert next_update(receiver, TIMEOUT_MS) == frame(1)
        time.sleep(2 * LATE_FRAME_MS / 1000)
        hand.by_pub(frame(1))
        assert next_update(receiver, 200) is None
        stats = receiver.stats
        assert (stats.copies, stats.late_copies, stats.saved) == (1, 1, 1)
        # A second-path copy after a gap (its queue dropped one) waits for the PUB's packets.
        hand.by_router(DeltaFrame(3, b"\x01"))
        assert next_update(receiver, 200) is None
        hand.by_pub(DeltaFrame(2, b"\x02"))
        hand.by_pub(DeltaFrame(3, b"\x01"))
        assert next_update(receiver, TIMEOUT_MS) == DeltaFrame(2, b"\x02")
        assert next_update(receiver, TIMEOUT_MS) == DeltaFrame(3, b"\x01")
        # Anything but a frame packet on the second path is counted and dropped.
        hand.by_router(KeyframeRequest(4))
        assert next_update(receiver, 200) is None
        assert receiver.stats.malformed == 1
        # The late copy was reported to the sender as a late frame: the link still loses.
        reports = []
        deadline = time.monotonic() + TIMEOUT_MS / 1000
        while not reports and time.monotonic() < deadline:
            if hand.router.poll(50):
                packet = decode(hand.router.recv_multipart()[1])
                if isinstance(packet, ReceiverStats):
                    reports.append(packet.values[LATE_FRAMES])
        assert reports == [1.0]
    finally:
        receiver.close()
        server.join()
        hand.close()


def test_a_rejoin_while_the_second_path_is_open_takes_each_frame_once(
    sender: SenderEndpoint, receiver: ReceiverEndpoint
) -> None:
    open_second_path(sender, receiver)
    for seq in range(1, 6):  # one at a time, as a call sends them: ROUTER queues only two
        sender.publish(frame(seq))
        frames_received(receiver, until_copies=seq)
    # Frames published while the receiver rejoins arrive over both paths; the old stream's
    # copies left on DEALER must not pass for the new stream's packets, and the new stream's
    # counters, which start over, are not copies of the old one's.
    for seq in range(6, 9):
        sender.publish(frame(seq))
    sender.set_snapshot(snapshot(seq=0))
    joined = threading.Event()

    def serve() -> None:  # the sender's loop answers probes and requests as it goes
        while not joined.is_set():
            sender.poll(10)

    server = threading.Thread(target=serve)
    server.start()
    try:
        assert receiver.fetch_snapshot(TIMEOUT_MS).seq == 0
    finally:
        joined.set()
        server.join()
    assert sender.spare_peers == 1  # the same connection: still open
    packets = [frame(seq) for seq in range(1, 21)]
    got = sent_one_at_a_time(sender, receiver, packets)
    copies = receiver.stats.copies
    got += frames_received(receiver, until_copies=copies + 1)
    assert got == packets
    assert receiver.stats.malformed == 0  # the old copies were a rejoin's, not bad input
