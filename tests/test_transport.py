"""ZeroMQ transport over real loopback sockets; synchronised by the protocol's handshake."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import pytest
import zmq
from transport_helpers import JPEG, TIMEOUT_MS, Context, FakeClock, frame, join, snapshot

from facewire.protocol.constants import HEARTBEAT_INTERVAL_S, PEER_TIMEOUT_S
from facewire.protocol.packets import (
    Bye,
    DeltaFrame,
    Heartbeat,
    KeyFrame,
    KeyframeRequest,
    ReceiverStats,
    RemPatch,
    Snapshot,
)
from facewire.protocol.transport import ReceiverEndpoint, SenderEndpoint, TransportError

Update = KeyFrame | DeltaFrame | RemPatch | Heartbeat | Bye | Snapshot


@pytest.fixture
def sender(context: Context) -> Iterator[SenderEndpoint]:
    s = SenderEndpoint(context=context, plain=True)
    yield s
    s.close()


def receiver_for(sender: SenderEndpoint, context: Context, **kw: object) -> ReceiverEndpoint:
    pub, snap = sender.ports
    return ReceiverEndpoint("127.0.0.1", pub, snap, context=context, plain=True, **kw)  # type: ignore[arg-type]


def deliver(
    sender: SenderEndpoint, receiver: ReceiverEndpoint, packets: list[Update], chunk: int = 16
) -> list[object]:
    """Publish ``packets`` a chunk at a time (a burst longer than UPDATE_HWM may be dropped by
    design) and return what the receiver accepted, without Heartbeats (probe answers)."""
    got: list[object] = []
    for start in range(0, len(packets), chunk):
        for packet in packets[start : start + chunk]:
            sender.publish(packet)
        # Every published update is either returned or counted as older than the snapshot.
        while len(got) + receiver.stats.dropped_old < min(start + chunk, len(packets)):
            received = receiver.recv(TIMEOUT_MS)
            assert received is not None, f"lost updates after {len(got)}"
            if not isinstance(received, Heartbeat):
                got.append(received)
    return got


def test_snapshot_then_300_frames_in_order(sender: SenderEndpoint, context: Context) -> None:
    sender.set_snapshot(snapshot(seq=0))
    with receiver_for(sender, context) as receiver:
        assert join(sender, receiver) == snapshot(seq=0)
        got = deliver(sender, receiver, [frame(seq) for seq in range(300)])
        assert [p.seq for p in got if isinstance(p, KeyFrame)] == list(range(300))
        assert got[123] == frame(123)
        assert receiver.stats.malformed == 0 and receiver.stats.dropped_old == 0
        assert receiver.bytes_received["geometry"] == sender.bytes_sent["geometry"]
        assert receiver.bytes_received["snapshot"] == len(bytes(snapshot(seq=0)))
        assert sender.bytes_sent["snapshot"] == len(bytes(snapshot(seq=0)))


def test_late_joiner_gets_snapshot_and_only_newer_updates(
    sender: SenderEndpoint, context: Context
) -> None:
    sender.set_snapshot(snapshot(seq=0))
    for seq in range(40):  # nobody listening: gone
        sender.publish(frame(seq))
    sender.set_snapshot(snapshot(seq=50))
    with receiver_for(sender, context) as receiver:
        assert join(sender, receiver).seq == 50
        updates: list[Update] = [frame(seq) for seq in range(40, 100)]  # 40..49: in flight
        updates += [
            RemPatch(45, "eye_left", "jpeg", JPEG, 10.0, 0.5, 0.5),
            RemPatch(60, "eye_left", "jpeg", JPEG, 10.0, 0.5, 0.5),
            DeltaFrame(1, b"\x01"),  # no seq: always passed on to the decoder
            Bye(99),
        ]
        got = deliver(sender, receiver, updates)
        assert [p.seq for p in got if isinstance(p, KeyFrame)] == list(range(50, 100))
        assert [p.seq for p in got if isinstance(p, RemPatch)] == [60]
        assert [p for p in got if isinstance(p, DeltaFrame)] == [DeltaFrame(1, b"\x01")]
        assert isinstance(got[-1], Bye)
        assert receiver.stats.dropped_old == 11
        assert not receiver.peer_alive  # said Bye


def test_malformed_updates_are_counted_dropped_and_survived(
    sender: SenderEndpoint, context: Context
) -> None:
    sender.set_snapshot(snapshot())
    with receiver_for(sender, context) as receiver:
        join(sender, receiver)
        raw = sender._pub  # inject bytes no well-behaved sender would publish
        sender.publish(frame(1))
        raw.send(b"")
        raw.send(b"\xc1garbage")
        raw.send(bytes(frame(2))[:5])  # truncated header
        raw.send_multipart([b"two", b"parts"])
        raw.send(bytes(KeyframeRequest(3)))  # well-formed but not an update
        sender.publish(frame(2))
        seqs: list[int] = []
        while len(seqs) < 2:
            packet = receiver.recv(TIMEOUT_MS)
            assert packet is not None
            if isinstance(packet, KeyFrame):
                seqs.append(packet.seq)
        assert seqs == [1, 2]
        assert receiver.stats.malformed == 5
        assert receiver.peer_alive


def test_back_channel_reaches_the_sender(sender: SenderEndpoint, context: Context) -> None:
    sender.set_snapshot(snapshot())
    with receiver_for(sender, context) as receiver:
        join(sender, receiver)
        receiver.request_keyframe(17)
        receiver.send_stats({"fps": 29.5, "latency_ms_p50": 31.0})
        got: list[object] = []
        while len(got) < 2:
            batch = sender.poll(TIMEOUT_MS)
            assert batch, "back channel packets lost"
            got.extend(batch)
        assert got == [KeyframeRequest(17), ReceiverStats({"fps": 29.5, "latency_ms_p50": 31.0})]
        assert sender.bytes_received["control"] > 0
        assert sender.stats.malformed == 0


def test_sender_survives_malformed_back_channel(sender: SenderEndpoint, context: Context) -> None:
    dealer = context.socket(zmq.DEALER)
    dealer.setsockopt(zmq.LINGER, 0)
    dealer.connect(f"tcp://127.0.0.1:{sender.ports[1]}")
    try:
        dealer.send(b"\xc1")
        dealer.send(bytes(frame(1)))  # an update on the back channel
        dealer.send(bytes(KeyframeRequest(5)))
        got: list[object] = []
        while not got:
            batch = sender.poll(TIMEOUT_MS)
            assert batch
            got.extend(batch)
        assert got == [KeyframeRequest(5)]
        assert sender.stats.malformed == 2
    finally:
        dealer.close(linger=0)


def test_snapshot_request_before_snapshot_is_answered_when_set(
    sender: SenderEndpoint, context: Context
) -> None:
    with receiver_for(sender, context) as receiver:
        result: list[Snapshot] = []
        thread = threading.Thread(target=lambda: result.append(receiver.fetch_snapshot(TIMEOUT_MS)))
        thread.start()
        try:
            # The receiver probes, then asks; the request waits for a snapshot.
            for _ in range(TIMEOUT_MS // 100):
                if sender._waiting:
                    break
                sender.poll(100)
            assert sender.snapshots_served == 0
            sender.set_snapshot(snapshot(seq=5))
        finally:
            thread.join()
        assert result == [snapshot(seq=5)]
        assert sender.snapshots_served == 1


def test_peer_lost_after_heartbeats_stop(context: Context) -> None:
    sender_clock, receiver_clock = FakeClock(), FakeClock()  # timing driven by hand
    sender = SenderEndpoint(context=context, clock=sender_clock, plain=True)
    sender.set_snapshot(snapshot())
    with sender, receiver_for(sender, context, clock=receiver_clock) as receiver:
        join(sender, receiver)
        assert receiver.peer_alive
        assert not sender.heartbeat_if_idle()  # the join probe's answer was just published
        sender_clock.t += HEARTBEAT_INTERVAL_S
        assert sender.heartbeat_if_idle()
        # Drain everything published so far; the last one is the idle heartbeat.
        received: list[Heartbeat] = []
        while not received or received[-1].sent_us != round(sender_clock.t * 1e6):
            packet = receiver.recv(TIMEOUT_MS)
            assert isinstance(packet, Heartbeat)
            received.append(packet)
        receiver_clock.t += PEER_TIMEOUT_S - 0.1
        assert receiver.peer_alive
        receiver_clock.t += 0.2  # no more packets: the sender went quiet
        assert receiver.recv(0) is None
        assert not receiver.peer_alive
        sender_clock.t += HEARTBEAT_INTERVAL_S
        assert sender.heartbeat_if_idle()
        assert isinstance(receiver.recv(TIMEOUT_MS), Heartbeat)
        assert receiver.peer_alive


def test_heartbeats_tell_the_last_frame_published(context: Context) -> None:
    clock = FakeClock()
    sender = SenderEndpoint(context=context, clock=clock, plain=True)
    sender.set_snapshot(snapshot())
    with sender, receiver_for(sender, context) as receiver:
        join(sender, receiver)
        sent = [(frame(10), None), (DeltaFrame(11, b"\x01"), 12), (DeltaFrame(12, b"\x02"), 15)]
        for packet, seq in sent:
            sender.publish(packet, seq=seq)
        sender.publish(DeltaFrame(13, b"\x03"))  # a delta without its number changes nothing
        clock.t += HEARTBEAT_INTERVAL_S
        assert sender.heartbeat_if_idle()
        heartbeats: list[Heartbeat] = []
        while not heartbeats or heartbeats[-1].sent_us != round(clock.t * 1e6):
            packet = receiver.recv(TIMEOUT_MS)
            assert packet is not None
            if isinstance(packet, Heartbeat):
                heartbeats.append(packet)
        assert heartbeats[-1].seq == 15  # not 10, the last keyframe's
        with pytest.raises(ValueError, match="frame number 4294967296 outside"):
            sender.publish(DeltaFrame(14, b""), seq=2**32)


def test_fetch_snapshot_times_out_without_sender(context: Context) -> None:
    with SenderEndpoint(context=context, plain=True) as probe_ports:
        pub, snap = probe_ports.ports
    # Nothing listens on those ports any more.
    with ReceiverEndpoint("127.0.0.1", pub, snap, context=context, plain=True) as receiver:
        with pytest.raises(TransportError) as info:
            receiver.fetch_snapshot(timeout_ms=200)
        # (A connection to a port nobody listens on can meet itself, TCP's simultaneous open:
        # the message then adds the failed handshake.)
        assert str(info.value).startswith(
            f"no published packet from tcp://127.0.0.1:{pub} within 200 ms (is the sender running?)"
        )
        with pytest.raises(TransportError, match=r"call fetch_snapshot\(\) before recv\(\)"):
            receiver.recv(0)


def test_wait_for_receiver_times_out(sender: SenderEndpoint) -> None:
    with pytest.raises(TransportError) as info:
        sender.wait_for_receiver(0.05)
    assert str(info.value) == "no receiver fetched the snapshot within 0.05 s (no snapshot set)"


def test_publish_rejects_back_channel_packets(sender: SenderEndpoint) -> None:
    with pytest.raises(TypeError, match="KeyframeRequest is not an update packet"):
        sender.publish(KeyframeRequest(1))  # type: ignore[arg-type]


def test_clean_close_frees_the_ports() -> None:
    # Own contexts: close() terminates them, which waits until the sockets are really gone.
    sender = SenderEndpoint(plain=True)
    sender.set_snapshot(snapshot())
    receiver = ReceiverEndpoint("127.0.0.1", *sender.ports, plain=True)
    join(sender, receiver)
    ports = sender.ports
    receiver.close()
    sender.close()
    sender.close()  # idempotent
    assert sender.closed and receiver.closed
    with pytest.raises(TransportError, match="SenderEndpoint is closed"):
        sender.publish(frame(1))
    with pytest.raises(TransportError, match="ReceiverEndpoint is closed"):
        receiver.recv(0)
    # linger 0: nothing holds the close up, and the ports can be bound again at once
    with SenderEndpoint(pub_port=ports[0], snapshot_port=ports[1], plain=True) as again:
        assert again.ports == ports
