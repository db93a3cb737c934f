"""The receiving end of a call: join, rebuild every frame, record, measure."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from protocol.channels import ChainBroken, FrameValues
from protocol.clock import now_us
from protocol.packets import Bye, DeltaFrame, KeyFrame, PacketError
from protocol.transport import ReceiverEndpoint
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
    **keys: Any,
) -> ReceiverReport:
    """Join the call at ``host``, record the rebuilt frames to ``output`` until Bye.

    ``keys`` go to :class:`~protocol.transport.ReceiverEndpoint` (``secret_key_file`` and
    ``server_key_file`` for CURVE, or ``plain=True``).

    Frame i of the recording rebuilds the sender's frame i: a frame with no packet (nothing
    changed, or the packet was lost) repeats the previous picture, so the recording stays
    aligned. When several packets are waiting, all are decoded (each delta needs the one
    before) but only the newest is rendered. After a gap the picture holds and a keyframe is
    requested until one arrives.
    """
    report = ReceiverReport()
    with ReceiverEndpoint(host, pub_port, snapshot_port, **keys) as endpoint:
        snapshot = endpoint.fetch_snapshot(timeout_ms=int(join_timeout_s * 1000))
        decoder = FaceDecoder(snapshot)
        # Tell the sender we can keep up from now on (building the decoder takes ~0.5 s), and
        # ask for the keyframe that starts our chain.
        endpoint.send_stats({"ready": 1.0})
        endpoint.request_keyframe(snapshot.seq)
        last_request = time.monotonic()
        next_seq = snapshot.seq
        last: np.ndarray | None = None
        try:
            with Mp4Recorder(output, snapshot.width, snapshot.height, snapshot.fps) as recorder:
                while True:
                    newest: FrameValues | None = None
                    packet = endpoint.recv(timeout_ms=200)
                    while packet is not None and not isinstance(packet, Bye):
                        if isinstance(packet, (KeyFrame, DeltaFrame)):
                            values = _decode(decoder, packet, report)
                            if values is not None and values.seq >= next_seq:
                                report.frames_skipped += newest is not None
                                newest = values
                        packet = endpoint.recv(timeout_ms=0)
                    if not decoder.channels.intact and (
                        time.monotonic() - last_request > KEYFRAME_RETRY_S
                    ):
                        endpoint.request_keyframe(next_seq)
                        report.keyframe_requests += 1
                        last_request = time.monotonic()
                    if newest is not None:
                        start = time.perf_counter()
                        report.frames_held += _hold(recorder, last, newest.seq - next_seq)
                        last = decoder.reconstruct(newest)
                        report.latency_ms.append((now_us() - newest.capture_us) / 1000.0)
                        recorder.write(last)
                        report.busy_s += time.perf_counter() - start
                        next_seq = newest.seq + 1
                    if isinstance(packet, Bye):
                        report.ended_by = "bye"
                        report.frames_held += _hold(recorder, last, packet.seq - next_seq)
                        break
                    if packet is None and newest is None and not endpoint.peer_alive:
                        report.ended_by = "peer lost"
                        break
                report.frames_out = recorder.frames
        finally:
            decoder.close()
        report.malformed += endpoint.stats.malformed
        report.bytes_received = dict(endpoint.bytes_received)
        report.bytes_sent = dict(endpoint.bytes_sent)
    return report


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
