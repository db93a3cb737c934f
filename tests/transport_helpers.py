"""Shared pieces of the transport tests: packets, key files, joining, waiting without sleep."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import zmq

from facewire.protocol.keys import write_keypair
from facewire.protocol.packets import KeyFrame, Snapshot
from facewire.protocol.transport import ReceiverEndpoint, SenderEndpoint

TIMEOUT_MS = 5000
#: A JPEG header (SOI, a 16 x 16 frame header, EOI): packets check image headers, and the
#: transport never decodes pixels.
JPEG = bytes.fromhex("ffd8ffc0000b080010001001011100ffd9")
SESSION = 7
Context = zmq.Context[zmq.Socket[bytes]]


class FakeClock:
    """A monotonic clock the test moves by hand (seconds)."""

    def __init__(self) -> None:
        self.t = 1000.0

    def __call__(self) -> float:
        return self.t


def snapshot(seq: int = 0, session_id: int = SESSION, texture: bytes = JPEG) -> Snapshot:
    return Snapshot(
        session_id=session_id,
        seq=seq,
        width=640,
        height=480,
        fps=30.0,
        vertices=np.arange(12, dtype=np.float32).reshape(4, 3),
        texture=texture,
        background=b"",
        channels=[("wire", 4, 0.001)],
        reference=[(0, 0, 0, 0)],
        rig_hash="ab" * 32,
        keyframe_interval=30,
    )


def frame(seq: int, session_id: int = SESSION, size: int = 8) -> KeyFrame:
    """A frame packet of about ``size`` + 18 bytes (the body is opaque to the transport)."""
    return KeyFrame(seq % 256, session_id, seq, seq * 33_333, bytes([seq % 251]) * size)


def keypairs(folder: Path, *names: str) -> dict[str, tuple[Path, Path]]:
    """name -> (public .key file, secret .key_secret file), all in ``folder``."""
    return {name: write_keypair(folder, name) for name in names}


def join(sender: SenderEndpoint, receiver: ReceiverEndpoint) -> Snapshot:
    """The demo's start-up: the sender waits for the receiver while the receiver joins."""
    errors: list[BaseException] = []

    def wait() -> None:
        try:
            sender.wait_for_receiver(TIMEOUT_MS / 1000)
        except BaseException as exc:  # reported in the main thread
            errors.append(exc)

    thread = threading.Thread(target=wait)
    thread.start()
    try:
        snap = receiver.fetch_snapshot(TIMEOUT_MS)
    finally:
        thread.join()
    if errors:
        raise errors[0]
    return snap


def rejoin(sender: SenderEndpoint, receiver: ReceiverEndpoint) -> Snapshot:
    """fetch_snapshot() again while another thread keeps the sender polling its back channel."""
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            sender.poll(20)

    thread = threading.Thread(target=serve)
    thread.start()
    try:
        return receiver.fetch_snapshot(TIMEOUT_MS)
    finally:
        stop.set()
        thread.join()


def wait_until(condition: Callable[[], bool], timeout_s: float, step: Callable[[], object]) -> bool:
    """Run ``step`` (which blocks briefly on a socket) until ``condition`` or the timeout."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        step()
    return True


def rss_bytes() -> int:
    """This process's resident set size (Linux /proc)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise OSError("no VmRSS in /proc/self/status")


def open_media_path(sender: SenderEndpoint, receiver: ReceiverEndpoint) -> None:
    """Until the path is open: the receiver's first hello and the sender's answer."""
    deadline = time.monotonic() + TIMEOUT_MS / 1000
    while not (receiver.on_udp and sender.media_figures()["receivers_on_udp"]):
        assert time.monotonic() < deadline, "the media path did not open"
        receiver.recv(10)
        sender.end_frame()
