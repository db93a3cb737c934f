"""A hostile peer against ``facewire receive --plain --bind``, as a user runs it.

The receiver and a real sender are facewire commands in their own processes; the attacker is
this test, with real ZeroMQ sockets on the receiver's bound ports: it answers the receiver's
snapshot requests with snapshots it cannot use, then, once the real session runs, connects
and leaves, publishes another session's packets, forged Byes, random bytes and messages of
8 MiB to SUB, and 16 MiB messages to DEALER. The receiver keeps its one session, counts what
it refused, keeps its memory, and SIGTERM still ends it with its figures and a playable
recording.
"""

from __future__ import annotations

import dataclasses
import json
import random
import time
from pathlib import Path

import zmq
from cli_call import Facewire, count_frames, free_ports, kill_all
from transport_helpers import snapshot

from facewire.models.face_channels import rig_hash
from facewire.protocol.packets import Bye, Heartbeat, KeyFrame, SnapshotRequest, decode

#: Peak memory the attacks may add to the receiver's (the README's bound).
MAX_EXTRA_BYTES = 150 * 1024 * 1024
WAIT_S = 60.0


def peak_rss(process: Facewire) -> int:
    """The process's peak resident set (VmHWM), bytes."""
    for line in Path(f"/proc/{process.process.pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    raise OSError("no VmHWM")


def said(process: Facewire, text: str) -> bool:
    return any(text in line for line in process.lines + process.stderr)


def until(condition: object, what: str, process: Facewire) -> None:
    deadline = time.monotonic() + WAIT_S
    while not condition():  # type: ignore[operator]
        assert time.monotonic() < deadline, f"{what}: {process.output()}"
        time.sleep(0.05)


def connected(context: zmq.Context, kind: int, port: int) -> zmq.Socket[bytes]:
    """A socket of ``kind`` connected to the receiver's ``port``, its handshake done."""
    sock = context.socket(kind)
    monitor = sock.get_monitor_socket(zmq.EVENT_HANDSHAKE_SUCCEEDED)
    try:
        sock.connect(f"tcp://127.0.0.1:{port}")
        assert monitor.poll(int(WAIT_S * 1000)), "no handshake"
    finally:
        sock.disable_monitor()
        monitor.close(linger=0)
    return sock


def answer_with_unusable_snapshots(context: zmq.Context, port: int, receiver: Facewire) -> None:
    """Before any sender: make the receiver's SUB readable, then answer its SnapshotRequests
    with a snapshot of another rig and one of this rig with another channel table."""
    unusable = [
        snapshot(session_id=1),  # rig "abab...": another rig
        dataclasses.replace(snapshot(session_id=2), rig_hash=rig_hash()),  # 4 wire values
    ]
    router = context.socket(zmq.ROUTER)
    publisher = context.socket(zmq.PUB)
    try:
        router.connect(f"tcp://127.0.0.1:{port + 1}")
        publisher.connect(f"tcp://127.0.0.1:{port}")
        deadline = time.monotonic() + WAIT_S
        while True:  # a request after the last answer: that one was refused too
            assert time.monotonic() < deadline, receiver.output()
            publisher.send(bytes(Heartbeat(1, 0, 0)))  # SUB has something: ask for a snapshot
            if not router.poll(50):
                continue
            identity, data = router.recv_multipart()
            if isinstance(decode(data), SnapshotRequest):
                if not unusable:
                    break
                router.send_multipart([identity, bytes(unusable.pop(0))])
        assert said(receiver, "refused session 1's snapshot"), receiver.output()
    finally:
        router.close(linger=0)
        publisher.close(linger=0)


def attack_the_session(context: zmq.Context, port: int) -> None:
    rng = random.Random(24)
    for _ in range(16):  # a port scan: connect, leave
        sock = connected(context, zmq.PUB, port)
        sock.close(linger=0)
    second = connected(context, zmq.PUB, port)
    for i in range(300):  # a second sender, a forger, noise: about 3 s
        for packet in (
            Heartbeat(rng.randrange(1 << 32), i, 0),
            KeyFrame(i % 256, rng.randrange(1 << 32), i, 0, b"\x00"),
            Bye(i),
            Bye(0xFFFFFFFF),
        ):
            second.send(bytes(packet))
        second.send(rng.randbytes(rng.randrange(1, 64)))
        time.sleep(0.01)
    second.close(linger=0)
    big = rng.randbytes(8 * 1024 * 1024)
    for _ in range(8):  # beyond what SUB takes: each ends the connection
        sock = connected(context, zmq.PUB, port)
        for _ in range(20):
            sock.send(big, copy=False)
            time.sleep(0.01)
        sock.close(linger=0)
    dealer = context.socket(zmq.DEALER)  # a stranger on the bound DEALER
    dealer.connect(f"tcp://127.0.0.1:{port + 1}")
    huge = b"\x21" * (16 * 1024 * 1024 - 64)
    for _ in range(16):
        dealer.send(huge, copy=False)
    time.sleep(1.0)
    dealer.close(linger=0)


def test_the_receiver_keeps_its_call_and_stops_cleanly(tmp_path: Path) -> None:
    port = free_ports(2)
    record, stats = tmp_path / "call.mp4", tmp_path / "stats.json"
    context = zmq.Context()
    receiver = sender = None
    try:
        receiver = Facewire(
            "receive", "--bind", f"tcp://127.0.0.1:{port}", "--plain",
            "--record", str(record), "--stats", str(stats),
        )  # fmt: skip
        receiver.expect("waiting for a sender")
        answer_with_unusable_snapshots(context, port, receiver)
        sender = Facewire("send", "--connect", f"tcp://127.0.0.1:{port}", "--plain", "--loop")
        receiver.expect("session ")
        sender.expect("a receiver joined")
        before = peak_rss(receiver)
        attack_the_session(context, port)
        extra = peak_rss(receiver) - before
        print(f"peak RSS {before / 2**20:.0f} MB before the attacks, +{extra / 2**20:.0f} MB")
        assert extra <= MAX_EXTRA_BYTES
        assert not said(receiver, "session ended"), receiver.output()
        asked = time.monotonic()
        receiver.signal()
        assert receiver.wait(timeout_s=10) == 0, receiver.output()
        print(f"SIGTERM to exit: {time.monotonic() - asked:.2f} s")
        sender.signal()
        assert sender.wait() == 0, sender.output()
    finally:
        kill_all(receiver, sender)
        context.destroy(linger=0)
    figures = json.loads(stats.read_text())
    print(
        {k: figures[k] for k in ("sessions", "refused_snapshots", "ignored_sessions", "malformed")}
    )
    assert figures["sessions"] == 1 and figures["ended_by"] == "stopped"
    assert figures["refused_snapshots"] == 2
    assert figures["ignored_sessions"] > 300
    assert count_frames(record) == figures["frames_out"] > 0
    refusal_lines = [line for line in receiver.stderr if "ignored" in line]
    assert len(refusal_lines) <= 2 + 10, "more than one line a second about what it ignored"
