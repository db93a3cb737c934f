"""Real calls for the recovery tests and benchmark.

A sender encodes the bundled clip at its frame rate over CURVE on loopback; receivers run
``facewire.receiver.session.run_receiver`` in their own processes (their own OpenGL context)
and record MP4s. Loss is injected by :class:`LossyLink`, a link with a loss pattern that
sits between the encoder and the real ``SenderEndpoint.publish``: everything after it
(sockets, receiver, keyframe requests over the back channel) is the real call.
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import queue
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.protocol.clock import now_us
from facewire.protocol.keys import write_keypair
from facewire.protocol.packets import DeltaFrame, KeyFrame, Refresh, RemPatch, Snapshot, decode
from facewire.protocol.transport import SenderEndpoint
from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path
from facewire.sender.encoder import FaceEncoder
from facewire.sender.session import SenderReport, run_sender, wait_until_ready

HOST = "127.0.0.1"
JOIN_TIMEOUT_S = 60.0
CTX = mp.get_context("spawn")  # fresh interpreters: no inherited sockets or GL state


@dataclass
class Keys:
    """A CURVE keypair for each end, in ``folder``."""

    folder: Path

    def __post_init__(self) -> None:
        self.sender_public, self.sender_secret = write_keypair(self.folder, "sender")
        self.receiver_public, self.receiver_secret = write_keypair(self.folder, "receiver")

    def sender(self) -> dict[str, Any]:
        return {"secret_key_file": self.sender_secret, "allowed_keys": [self.receiver_public]}

    def receiver(self) -> dict[str, Any]:
        return {
            "secret_key_file": str(self.receiver_secret),
            "server_key_file": str(self.sender_public),
        }


@dataclass
class LossyLink:
    """Publishes frame packets and REM patches unless ``drop(seq)`` says the network lost
    that frame's packets.

    Every packet is also kept in ``sent`` (with its frame's seq), lost or not, so a test can
    rebuild what a lossless receiver would show.
    """

    endpoint: SenderEndpoint
    drop: Callable[[int], bool] = lambda seq: False
    seq: int = 0  # the frame being sent (set by :meth:`frames`)
    sent: list[tuple[int, bytes]] = field(default_factory=list)
    lost: list[int] = field(default_factory=list)

    def frames(self, frames: Iterable[CapturedFrame]) -> Iterator[CapturedFrame]:
        for frame in frames:
            self.seq = frame.index
            yield frame

    def __call__(self, packet: KeyFrame | DeltaFrame | RemPatch) -> None:
        self.sent.append((self.seq, bytes(packet)))
        if self.drop(self.seq):
            self.lost.append(self.seq)
        else:
            self.endpoint.publish(packet)


def _receiver_main(ports: tuple[int, int], output: str, options: dict, results: Any) -> None:
    from facewire.receiver.session import run_receiver

    try:
        report = run_receiver(HOST, *ports, output, join_timeout_s=JOIN_TIMEOUT_S, **options)
        results.put(("ok", report.as_dict()))
    except Exception as exc:
        results.put(("error", f"{type(exc).__name__}: {exc}"))


class ReceiverProcess:
    """``run_receiver`` in a child process; :meth:`report` waits for what it measured."""

    def __init__(self, ports: tuple[int, int], output: Path, **options: Any) -> None:
        self._results = CTX.Queue()
        self.process = CTX.Process(
            target=_receiver_main, args=(ports, str(output), options, self._results)
        )
        self.process.start()

    def report(self, timeout_s: float = 60.0) -> dict[str, Any]:
        try:
            status, detail = self._results.get(timeout=timeout_s)
        except queue.Empty:
            raise AssertionError(f"the receiver did not finish within {timeout_s:g} s") from None
        finally:
            self.process.join(timeout=10)
            if self.process.is_alive():
                self.process.kill()
        assert status == "ok", detail
        return detail

    def kill(self) -> None:
        self.process.kill()
        self.process.join(timeout=10)


def start_sender(
    frames: int | None = None,
) -> tuple[FaceEncoder, Snapshot, Iterator[CapturedFrame]]:
    """An encoder started on the bundled clip, its snapshot, and the frames still to send
    (read at the clip's frame rate, as a camera would give them, but every one of them however
    late: these tests follow the call frame by frame)."""
    video = VideoSource(demo_clip_path(), realtime=True, keep_late=True)
    # No refreshes (tests/test_refresh.py has them): one of a few hundred bytes crosses a paced
    # link in several datagrams and shows some frames after its own, which reference_frames,
    # every packet drawn at its frame, cannot know. (The bundled clip's hair stays still while
    # its head moves: the model's moving hair sends refreshes.)
    encoder = FaceEncoder(video.width, video.height, video.fps, refresh=False)
    it = video.frames(limit=frames)
    first = next(it)
    snapshot = encoder.start(first, seq=0)
    assert snapshot is not None, "no face in the bundled clip's first frame"

    def rest() -> Iterator[CapturedFrame]:
        # Pacing (and the capture clock) start when the call does.
        with video:
            video.resync(1)
            yield dataclasses.replace(first, capture_us=now_us())
            yield from it

    return encoder, snapshot, rest()


def send(
    endpoint: SenderEndpoint,
    encoder: FaceEncoder,
    frames: Iterable[CapturedFrame],
    link: LossyLink | None = None,
) -> SenderReport:
    """``run_sender`` through ``link`` (lossless if None)."""
    if link is None:
        return run_sender(endpoint, encoder, frames)
    return run_sender(endpoint, encoder, link.frames(frames), publish=link)


def _sender_main(
    ports: tuple[int, int], keys: Keys, frames: int, announce: int, results: Any
) -> None:
    try:
        encoder, snapshot, rest = start_sender(frames)
        with SenderEndpoint(HOST, *ports, **keys.sender()) as endpoint:
            endpoint.set_snapshot(snapshot)
            results.put(("ports", endpoint.ports))
            if not wait_until_ready(endpoint, JOIN_TIMEOUT_S):
                raise RuntimeError("no receiver joined")
            results.put(("sending", snapshot.session_id))
            report = run_sender(endpoint, encoder, _announcing(rest, announce, results))
        results.put(("ok", report.frames_in))
    except Exception as exc:
        results.put(("error", f"{type(exc).__name__}: {exc}"))


def _announcing(
    frames: Iterable[CapturedFrame], announce: int, results: Any
) -> Iterator[CapturedFrame]:
    for frame in frames:
        if frame.index == announce:
            results.put(("frame", announce))  # this frame is about to be sent
        yield frame


class SenderProcess:
    """A sender of the bundled clip in a child process (so a test can kill it). It reports
    "ports" when bound, "sending" when a receiver is ready, "frame" when it reaches frame
    ``announce`` and "ok" at the end."""

    def __init__(
        self, keys: Keys, frames: int, ports: tuple[int, int] = (0, 0), announce: int = -1
    ) -> None:
        self._results = CTX.Queue()
        self.process = CTX.Process(
            target=_sender_main, args=(ports, keys, frames, announce, self._results)
        )
        self.process.start()
        self.ports: tuple[int, int] = self.expect("ports")

    def expect(self, what: str, timeout_s: float = JOIN_TIMEOUT_S) -> Any:
        """Wait for the child to report ``what``; returns what came with it."""
        try:
            status, detail = self._results.get(timeout=timeout_s)
        except queue.Empty:
            raise AssertionError(f"the sender did not report {what!r} in {timeout_s:g} s") from None
        assert status == what, detail
        return detail

    def kill(self) -> None:
        self.process.kill()
        self.process.join(timeout=10)


def wait_ready(endpoint: SenderEndpoint, receiver: ReceiverProcess) -> None:
    assert wait_until_ready(endpoint, JOIN_TIMEOUT_S, receiver.process.is_alive), (
        "the receiver did not join"
    )


def reference_frames(snapshot: Snapshot, sent: list[tuple[int, bytes]]) -> dict[int, np.ndarray]:
    """seq -> the picture a receiver that lost nothing renders for that frame's packet (with
    the REM patches sent up to it)."""
    from facewire.receiver.decoder import FaceDecoder

    decoder = FaceDecoder(snapshot)
    try:
        out = {}
        for seq, data in sent:
            packet = decode(data)
            if isinstance(packet, RemPatch):
                assert decoder.add_patch(packet)
                continue
            if isinstance(packet, Refresh):
                assert decoder.add_refresh(packet)
                continue
            assert isinstance(packet, (KeyFrame, DeltaFrame))
            out[seq] = decoder.reconstruct(decoder.decode(packet))
        return out
    finally:
        decoder.close()


def read_video(path: Path) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    frames = []
    try:
        while True:
            ok, image = capture.read()
            if not ok:
                return frames
            frames.append(image)
    finally:
        capture.release()


def mean_abs_diff(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())
