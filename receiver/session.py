"""The receiving end of a call: join, rebuild every frame, record, measure."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from protocol.channels import ChainBroken, FrameValues
from protocol.clock import now_us
from protocol.packets import Bye, DeltaFrame, KeyFrame, PacketError, Snapshot
from protocol.transport import ReceiverEndpoint, RejoinNeeded, TransportError
from receiver.decoder import FaceDecoder
from receiver.recorder import Mp4Recorder

logger = logging.getLogger(__name__)

#: The most frames one gap may fill with the held picture (beyond it the recording jumps:
#: a hostile or broken sequence number must not write millions of frames).
MAX_HOLD_FRAMES = 300
#: Keyframe requests while the chain is broken are repeated at most this often.
KEYFRAME_RETRY_S = 0.25


@dataclass
class ReceiverReport:
    """What the receiving side measured over one call."""

    frames_out: int = 0
    frames_held: int = 0  # written again: no packet (nothing changed, or lost)
    frames_skipped: int = 0  # decoded but not rendered: a newer frame was already waiting
    keyframe_requests: int = 0
    chain_breaks: int = 0
    sessions: int = 0  # sessions joined (a restarted sender starts a new one)
    # Runs of frames shown stale because packets were lost: (first seq, frames) per run.
    freezes: list[tuple[int, int]] = field(default_factory=list)
    # Per session: seconds from asking for its snapshot to its first rendered frame.
    first_frame_s: list[float] = field(default_factory=list)
    busy_s: float = 0.0  # own processing time: deform + render + record
    latency_ms: list[float] = field(default_factory=list)
    malformed: int = 0
    bytes_received: dict[str, int] = field(default_factory=dict)
    bytes_sent: dict[str, int] = field(default_factory=dict)
    ended_by: str = ""

    def as_dict(self) -> dict:
        lat = np.asarray(self.latency_ms) if self.latency_ms else np.zeros(1)
        return {
            "frames_out": self.frames_out,
            "frames_held": self.frames_held,
            "frames_skipped": self.frames_skipped,
            "keyframe_requests": self.keyframe_requests,
            "chain_breaks": self.chain_breaks,
            "sessions": self.sessions,
            "freezes": [list(f) for f in self.freezes],
            "first_frame_s": list(self.first_frame_s),
            "receiver_fps": self.frames_out / self.busy_s if self.busy_s > 0 else 0.0,
            "latency_ms": {
                "p50": float(np.percentile(lat, 50)),
                "p99": float(np.percentile(lat, 99)),
                "max": float(lat.max()),
            },
            "malformed": self.malformed,
            "bytes_received": dict(self.bytes_received),
            "bytes_sent": dict(self.bytes_sent),
            "ended_by": self.ended_by,
        }


def run_receiver(
    host: str,
    pub_port: int,
    snapshot_port: int,
    output: str,
    join_timeout_s: float = 20.0,
    rejoin_timeout_s: float = 0.0,
    **keys: Any,
) -> ReceiverReport:
    """Join the call at ``host`` and record the rebuilt frames to ``output``.

    ``keys`` go to :class:`~protocol.transport.ReceiverEndpoint` (``secret_key_file`` and
    ``server_key_file`` for CURVE, or ``plain=True``).

    Frame i of the recording rebuilds the sender's frame i: a frame with no packet (nothing
    changed, or the packet was lost) repeats the previous picture, so the recording stays
    aligned. When several packets are waiting, all are decoded (each delta needs the one
    before) but only the newest is rendered. After a gap the picture holds and a keyframe is
    requested until one arrives.

    A session ends with the sender's Bye, when the sender is silent for PEER_TIMEOUT_S, or when
    it restarts (a new session on the same address). With ``rejoin_timeout_s`` > 0 the
    receiver then waits that long for the next session and records it on, scaled to the
    recording's size; otherwise the call ends.
    """
    report = ReceiverReport()
    with ReceiverEndpoint(host, pub_port, snapshot_port, **keys) as endpoint:
        started = time.monotonic()
        snapshot: Snapshot | None = endpoint.fetch_snapshot(timeout_ms=_ms(join_timeout_s))
        assert snapshot is not None
        with Mp4Recorder(output, snapshot.width, snapshot.height, snapshot.fps) as recorder:
            while snapshot is not None:
                report.sessions += 1
                report.ended_by = _receive_session(endpoint, snapshot, recorder, report, started)
                snapshot = None
                if rejoin_timeout_s > 0:
                    logger.info("%s: waiting for a new session", report.ended_by)
                    started = time.monotonic()
                    try:
                        snapshot = endpoint.fetch_snapshot(timeout_ms=_ms(rejoin_timeout_s))
                    except TransportError as exc:
                        logger.info("no new session: %s", exc)
            report.frames_out = recorder.frames
        report.malformed += endpoint.stats.malformed
        report.bytes_received = dict(endpoint.bytes_received)
        report.bytes_sent = dict(endpoint.bytes_sent)
    return report


def _receive_session(
    endpoint: ReceiverEndpoint,
    snapshot: Snapshot,
    recorder: Mp4Recorder,
    report: ReceiverReport,
    started: float,
) -> str:
    """Rebuild and record one session's frames; returns why it ended."""
    decoder = FaceDecoder(snapshot)
    try:
        # Tell the sender we can keep up from now on (building the decoder takes ~0.5 s), and
        # ask for the keyframe that starts our chain.
        endpoint.send_stats({"ready": 1.0})
        endpoint.request_keyframe(snapshot.seq)
        last_request = time.monotonic()
        next_seq = snapshot.seq
        stale_from: int | None = None  # first frame shown stale because the chain broke
        last: np.ndarray | None = None
        while True:
            newest: FrameValues | None = None
            try:
                packet = endpoint.recv(timeout_ms=200)
                while packet is not None and not isinstance(packet, Bye):
                    if isinstance(packet, (KeyFrame, DeltaFrame)):
                        values = _decode(decoder, packet, report)
                        if values is not None and values.seq >= next_seq:
                            report.frames_skipped += newest is not None
                            newest = values
                    packet = endpoint.recv(timeout_ms=0)
            except RejoinNeeded as exc:
                return f"sender restarted ({exc})"
            if not decoder.channels.intact:
                if stale_from is None and last is not None:
                    stale_from = next_seq
                if time.monotonic() - last_request > KEYFRAME_RETRY_S:
                    endpoint.request_keyframe(next_seq)
                    report.keyframe_requests += 1
                    last_request = time.monotonic()
            if newest is not None:
                start = time.perf_counter()
                report.frames_held += _hold(recorder, last, newest.seq - next_seq)
                if stale_from is not None:
                    report.freezes.append((stale_from, newest.seq - stale_from))
                    stale_from = None
                picture = _fit(decoder.reconstruct(newest), recorder.size)
                if last is None:
                    report.first_frame_s.append(time.monotonic() - started)
                    # Frames of the session's first second that came before its first
                    # decodable packet show that first picture, so the recording stays
                    # aligned; a late joiner's recording starts where it joined.
                    early = newest.seq - next_seq
                    if early <= snapshot.fps:
                        report.frames_held += _hold(recorder, picture, early)
                last = picture
                report.latency_ms.append((now_us() - newest.capture_us) / 1000.0)
                recorder.write(last)
                report.busy_s += time.perf_counter() - start
                next_seq = newest.seq + 1
            if isinstance(packet, Bye):
                report.frames_held += _hold(recorder, last, packet.seq - next_seq)
                return "bye"
            if packet is None and newest is None and not endpoint.peer_alive:
                return "peer lost"
    finally:
        decoder.close()


def _ms(seconds: float) -> int:
    return max(1, round(seconds * 1000))


def _fit(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` at the recording's (width, height): a later session may have another size."""
    return image if image.shape[1::-1] == size else cv2.resize(image, size)


def _decode(
    decoder: FaceDecoder, packet: KeyFrame | DeltaFrame, report: ReceiverReport
) -> FrameValues | None:
    try:
        return decoder.decode(packet)
    except ChainBroken as exc:
        logger.debug("%s", exc)
        report.chain_breaks += 1
    except PacketError as exc:
        logger.debug("dropped frame packet: %s", exc)
        report.malformed += 1
    return None


def _hold(recorder: Mp4Recorder, last: np.ndarray | None, count: int) -> int:
    """Write the previous picture for ``count`` frames that had no packet (at most
    MAX_HOLD_FRAMES: a longer gap is a jump, not a still picture)."""
    if last is None or count <= 0:
        return 0
    if count > MAX_HOLD_FRAMES:
        logger.warning("gap of %d frames: holding only %d", count, MAX_HOLD_FRAMES)
        count = MAX_HOLD_FRAMES
    for _ in range(count):
        recorder.write(last)
    return count
