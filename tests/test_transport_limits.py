"""Bounded memory under slow or hostile peers; probes cannot multiply published traffic.

The peers that never read run in child processes, so that this process's resident memory is
the sender's alone. Memory bounds are loose (tens of MB) and nothing here asserts a duration.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zmq
from transport_helpers import JPEG, TIMEOUT_MS, Context, frame, join, rss_bytes, snapshot

from facewire.protocol.constants import (
    MAX_SNAPSHOT_PEERS,
    PROBE_INTERVAL_MS,
    SNAPSHOT_MIN_INTERVAL_S,
)
from facewire.protocol.packets import Heartbeat, KeyFrame, SnapshotRequest
from facewire.protocol.transport import ReceiverEndpoint, SenderEndpoint

ROOT = Path(__file__).resolve().parents[1]
MB = 1024 * 1024

# A receiver that joins, says so, and never reads again (until its stdin closes).
STALLED_RECEIVER = """
import sys
from facewire.protocol.transport import ReceiverEndpoint
with ReceiverEndpoint("127.0.0.1", int(sys.argv[1]), int(sys.argv[2]), plain=True) as r:
    r.fetch_snapshot(10000)
    print("joined", flush=True)
    sys.stdin.read()
"""

# A peer that asks for the snapshot again and again and never reads a reply.
SNAPSHOT_FLOOD = """
import sys, zmq
from facewire.protocol.packets import SnapshotRequest
ctx = zmq.Context()
dealer = ctx.socket(zmq.DEALER)
dealer.linger = 0
dealer.connect(f"tcp://127.0.0.1:{sys.argv[1]}")
request = bytes(SnapshotRequest())
for _ in range(int(sys.argv[2])):
    dealer.send(request)
print("sent", flush=True)
sys.stdin.read()
"""


def child(script: str, *args: object) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", script, *map(str, args)],
        cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )


def end(proc: subprocess.Popen[str]) -> None:
    assert proc.stdin is not None
    proc.stdin.close()
    try:
        proc.wait(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


@pytest.fixture
def sender() -> Iterator[SenderEndpoint]:
    with SenderEndpoint(plain=True) as s:
        yield s


def test_stalled_receiver_does_not_grow_sender_memory(sender: SenderEndpoint) -> None:
    sender.set_snapshot(snapshot())
    proc = child(STALLED_RECEIVER, *sender.ports)
    try:
        sender.wait_for_receiver(20)
        frames = [frame(seq, size=82) for seq in range(20_000)]  # 100 bytes each
        assert len(bytes(frames[0])) == 100
        before = rss_bytes()
        for packet in frames:
            sender.publish(packet)
        growth = rss_bytes() - before
        print(f"sender RSS growth after 20000 x 100 B to a stalled receiver: {growth / MB:.1f} MB")
        assert growth < 50 * MB
    finally:
        end(proc)


def test_snapshot_request_flood_is_rate_limited(sender: SenderEndpoint) -> None:
    texture = JPEG + bytes(60_000)  # a realistic 60 kB snapshot
    sender.set_snapshot(snapshot(texture=texture))
    proc = child(SNAPSHOT_FLOOD, sender.ports[1], 10_000)
    try:
        before = rss_bytes()
        started = time.monotonic()
        deadline = started + 60
        while sender.stats.received < 10_000 and time.monotonic() < deadline:
            sender.poll(100)
        elapsed = time.monotonic() - started
        growth = rss_bytes() - before
        print(
            f"10000 snapshot requests in {elapsed:.1f} s: {sender.snapshots_served} served, "
            f"{sender.snapshots_refused} refused, sender RSS growth {growth / MB:.1f} MB"
        )
        assert sender.stats.received == 10_000
        assert sender.snapshots_served + sender.snapshots_refused == 10_000
        assert sender.snapshots_served <= elapsed / 0.5 + 1
        assert growth < 50 * MB
    finally:
        end(proc)


def test_probe_flood_publishes_few_heartbeats(sender: SenderEndpoint) -> None:
    sender.set_snapshot(snapshot())
    context: Context = zmq.Context()
    probes = 100_000

    def flood() -> None:
        dealer = context.socket(zmq.DEALER)
        dealer.setsockopt(zmq.LINGER, 0)
        dealer.connect(f"tcp://127.0.0.1:{sender.ports[1]}")
        probe = bytes(Heartbeat(0, 0, 0))
        for _ in range(probes):
            dealer.send(probe)  # blocks while the sender's small queue is full
        dealer.close()

    with ReceiverEndpoint("127.0.0.1", *sender.ports, context=context, plain=True) as receiver:
        join(sender, receiver)
        while receiver.recv(0) is not None:  # the answers to the join probes
            pass
        base = sender.stats.received
        thread = threading.Thread(target=flood)
        started = time.monotonic()
        thread.start()
        heartbeats, seqs, published = 0, [], 0
        deadline = started + 120
        while sender.stats.received - base < probes and time.monotonic() < deadline:
            sender.publish(frame(published))
            published += 1
            sender.poll(5)
            while (packet := receiver.recv(0)) is not None:
                heartbeats += isinstance(packet, Heartbeat)
                if isinstance(packet, KeyFrame):
                    seqs.append(packet.seq)
        elapsed = time.monotonic() - started
        thread.join()
        while len(seqs) < published:
            packet = receiver.recv(TIMEOUT_MS)
            assert packet is not None, f"lost frames: {len(seqs)} of {published}"
            heartbeats += isinstance(packet, Heartbeat)
            if isinstance(packet, KeyFrame):
                seqs.append(packet.seq)
        print(
            f"{probes} probes in {elapsed:.1f} s: {heartbeats} heartbeats published, "
            f"{sender.probes_unanswered} probes unanswered, {published} frames all delivered"
        )
        assert sender.stats.received - base == probes
        assert heartbeats <= elapsed / (PROBE_INTERVAL_MS / 1000) + 2
        assert seqs == list(range(published))
    context.term()


def test_snapshot_requests_before_a_snapshot_are_bounded(sender: SenderEndpoint) -> None:
    context: Context = zmq.Context()
    dealers = [context.socket(zmq.DEALER) for _ in range(3)]
    try:
        for dealer in dealers:
            dealer.setsockopt(zmq.LINGER, 0)
            dealer.connect(f"tcp://127.0.0.1:{sender.ports[1]}")
            for _ in range(50):
                dealer.send(bytes(SnapshotRequest()))
        deadline = time.monotonic() + 10
        while sender.stats.received < 150 and time.monotonic() < deadline:
            sender.poll(100)
        assert len(sender._waiting) == 3  # one entry per peer, however often it asked
        sender.set_snapshot(snapshot())
        assert sender.snapshots_served == 3
    finally:
        for dealer in dealers:
            dealer.close(linger=0)
        context.term()


def test_receivers_served_long_ago_are_forgotten(sender: SenderEndpoint) -> None:
    """Each connection is a new identity: a sender that runs for days keeps a record of what
    it served for the last MAX_SNAPSHOT_PEERS receivers, not for every connection made."""
    sender.set_snapshot(snapshot())
    context: Context = zmq.Context()
    dealers: list[zmq.Socket] = []
    try:
        for batch in range(1, 4):  # 450 receivers, 150 at a time
            for _ in range(150):
                dealer = context.socket(zmq.DEALER)
                dealer.setsockopt(zmq.LINGER, 0)
                dealer.connect(f"tcp://127.0.0.1:{sender.ports[1]}")
                dealer.send(bytes(SnapshotRequest()))
                dealers.append(dealer)
            deadline = time.monotonic() + 20
            while sender.snapshots_served < 150 * batch and time.monotonic() < deadline:
                sender.poll(100)
            # Not "too many peers asking at once": the last batch's requests are old now.
            time.sleep(SNAPSHOT_MIN_INTERVAL_S)
        assert sender.snapshots_served == 450
        assert len(sender._served_what) == MAX_SNAPSHOT_PEERS
    finally:
        for dealer in dealers:
            dealer.close(linger=0)
        context.term()
