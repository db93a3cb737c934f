"""The sending end of a call: encode every frame, publish it, answer the back channel."""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

from protocol.packets import Bye, DeltaFrame, KeyFrame, KeyframeRequest, ReceiverStats
from protocol.transport import SenderEndpoint, TransportError
from sender.capture import CapturedFrame
from sender.encoder import FaceEncoder

logger = logging.getLogger(__name__)

FramePacket = KeyFrame | DeltaFrame


@dataclass
class SenderReport:
    """What the sending side measured over one call."""

    frames_in: int = 0
    packets: int = 0  # frame packets handed to the link (no packet: nothing changed)
    keyframe_requests: int = 0
    busy_s: float = 0.0  # own processing time: track + encode + publish
    receiver_stats: dict[str, float] = field(default_factory=dict)  # the latest of each name

    @property
    def fps(self) -> float:
        return self.frames_in / self.busy_s if self.busy_s > 0 else 0.0


def run_sender(
    endpoint: SenderEndpoint,
    encoder: FaceEncoder,
    frames: Iterable[CapturedFrame],
    publish: Callable[[FramePacket], None] | None = None,
) -> SenderReport:
    """Encode and publish every frame of ``frames``, then say Bye.

    ``encoder`` has started (its snapshot is set on ``endpoint``). Between frames the back
    channel is read: a KeyframeRequest makes the next packet a keyframe, ReceiverStats are kept
    in the report. Heartbeats go out when nothing was published for a second. ``publish``
    replaces ``endpoint.publish`` for frame packets (a test's lossy link).
    """
    send = publish or endpoint.publish
    report = SenderReport()
    next_seq = 0
    for frame in frames:
        _read_back_channel(endpoint, encoder, report)
        start = time.perf_counter()
        packet = encoder.encode(frame)
        if packet is not None:  # None: nothing visible changed since the last packet
            send(packet)
            report.packets += 1
        report.busy_s += time.perf_counter() - start
        report.frames_in += 1
        next_seq = frame.index + 1
        endpoint.heartbeat_if_idle()
    endpoint.publish(Bye(seq=next_seq))
    _read_back_channel(endpoint, encoder, report)
    return report


def wait_until_ready(
    endpoint: SenderEndpoint, timeout_s: float, keep_waiting: Callable[[], bool] = lambda: True
) -> bool:
    """Until a receiver has fetched the snapshot and says it is ready to render (building its
    renderer takes a while: frames sent before then would only queue up as latency).

    False after ``timeout_s``, or as soon as ``keep_waiting()`` is False.
    """
    deadline = time.monotonic() + timeout_s
    joined = False
    while keep_waiting() and time.monotonic() < deadline:
        if not joined:
            try:
                endpoint.wait_for_receiver(timeout_s=0.5)
                joined = True
            except TransportError:
                continue
        for packet in endpoint.poll(timeout_ms=100):
            if isinstance(packet, ReceiverStats) and packet.values.get("ready"):
                return True
    return False


def _read_back_channel(
    endpoint: SenderEndpoint, encoder: FaceEncoder, report: SenderReport
) -> None:
    for packet in endpoint.poll(0):
        if isinstance(packet, KeyframeRequest):
            logger.debug("keyframe requested after seq %d", packet.seq)
            encoder.request_keyframe()
            report.keyframe_requests += 1
        elif isinstance(packet, ReceiverStats):
            report.receiver_stats.update(packet.values)
