"""Sender memory against peers that never read, and published heartbeats under a probe flood.

Usage: python benchmarks/bench_slow_receiver.py

1. A receiver joins and then never reads while the sender publishes 20 000 frames (100 B and
   10 kB). 2. A peer sends 10 000 SnapshotRequests (60 kB snapshot) and never reads a reply.
3. A peer sends 100 000 probes. The slow peers run in child processes, so the figures are the
sender's own resident memory (VmRSS).
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zmq

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from facewire.protocol.packets import Heartbeat, KeyFrame, Snapshot  # noqa: E402
from facewire.protocol.transport import SenderEndpoint  # noqa: E402

MB = 1024 * 1024
#: SOI, a 16 x 16 frame header, EOI: a texture whose header packets accept (never decoded here).
JPEG_HEADER = bytes.fromhex("ffd8ffc0000b080010001001011100ffd9")
STALLED_RECEIVER = """
import sys
from facewire.protocol.transport import ReceiverEndpoint
with ReceiverEndpoint("127.0.0.1", int(sys.argv[1]), int(sys.argv[2]), plain=True) as r:
    r.fetch_snapshot(10000)
    sys.stdin.read()
"""
SNAPSHOT_FLOOD = """
import sys, zmq
from facewire.protocol.packets import SnapshotRequest
dealer = zmq.Context().socket(zmq.DEALER)
dealer.linger = 0
dealer.connect(f"tcp://127.0.0.1:{sys.argv[1]}")
for _ in range(int(sys.argv[2])):
    dealer.send(bytes(SnapshotRequest()))
sys.stdin.read()
"""


def rss() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise OSError("no VmRSS")


def snapshot(texture_bytes: int) -> Snapshot:
    return Snapshot(
        session_id=1,
        seq=0,
        width=640,
        height=480,
        fps=30.0,
        vertices=np.zeros((468, 3), np.float32),
        texture=JPEG_HEADER + bytes(texture_bytes),
        background=b"",
        channels=[("wire", 4, 0.001)],
        reference=[(0, 0, 0, 0)],
        rig_hash="ab" * 32,
        keyframe_interval=30,
    )


def child(script: str, *args: object) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-c", script, *map(str, args)],
        cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"},
        stdin=subprocess.PIPE,
        text=True,
    )


def end(proc: subprocess.Popen[str]) -> None:
    assert proc.stdin is not None
    proc.stdin.close()
    proc.wait(timeout=10)


def stalled_receiver(body: int, count: int = 20_000) -> None:
    with SenderEndpoint(plain=True) as sender:
        sender.set_snapshot(snapshot(1000))
        proc = child(STALLED_RECEIVER, *sender.ports)
        sender.wait_for_receiver(20)
        frames = [KeyFrame(i % 256, 1, i, i, bytes(body)) for i in range(count)]
        before = rss()
        for packet in frames:
            sender.publish(packet)
        time.sleep(0.5)  # let the I/O thread queue what it will (a figure, not a test)
        after = rss()
        end(proc)
    size = len(bytes(frames[0]))
    print(
        f"stalled receiver, {count} x {size} B frames: sender RSS "
        f"{before / MB:.0f} -> {after / MB:.0f} MiB (+{(after - before) / MB:.1f})"
    )


def snapshot_flood(count: int = 10_000) -> None:
    with SenderEndpoint(plain=True) as sender:
        sender.set_snapshot(snapshot(60_000))
        proc = child(SNAPSHOT_FLOOD, sender.ports[1], count)
        before = rss()
        deadline = time.monotonic() + 120
        while sender.stats.received < count and time.monotonic() < deadline:
            sender.poll(100)
        after = rss()
        served = sender.snapshots_served
        refused = getattr(sender, "snapshots_refused", 0)
        end(proc)
    print(
        f"{count} snapshot requests (60 kB snapshot), replies never read: {served} served, "
        f"{refused} refused, sender RSS {before / MB:.0f} -> {after / MB:.0f} MiB "
        f"(+{(after - before) / MB:.1f})"
    )


def probe_flood(count: int = 100_000) -> None:
    with SenderEndpoint(plain=True) as sender:
        context: zmq.Context[zmq.Socket[bytes]] = zmq.Context()
        sub = context.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        sub.connect(f"tcp://127.0.0.1:{sender.ports[0]}")

        def flood() -> None:
            dealer = context.socket(zmq.DEALER)
            dealer.setsockopt(zmq.LINGER, 0)
            dealer.connect(f"tcp://127.0.0.1:{sender.ports[1]}")
            for _ in range(count):
                dealer.send(bytes(Heartbeat(0, 0, 0)))
            dealer.close()

        thread = threading.Thread(target=flood)
        start = time.monotonic()
        thread.start()
        published = 0
        while sender.stats.received < count and time.monotonic() - start < 120:
            sender.poll(10)
            while sub.poll(0):
                sub.recv()
                published += 1
        elapsed = time.monotonic() - start
        thread.join()
        while sub.poll(200):
            sub.recv()
            published += 1
        sub.close()
        context.term()
    print(f"{count} probes in {elapsed:.1f} s: {published} heartbeats published")


def main() -> None:
    stalled_receiver(82)
    stalled_receiver(10_000)
    snapshot_flood()
    probe_flood()


if __name__ == "__main__":
    main()
