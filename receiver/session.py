"""The receiving end of a call: join, rebuild every frame, record, measure."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np

from protocol.clock import now_us
from protocol.packets import Bye, Frame
from protocol.transport import ReceiverEndpoint
from receiver.decoder import FaceDecoder
from receiver.recorder import Mp4Recorder

logger = logging.getLogger(__name__)


@dataclass
class ReceiverReport:
    """What the receiving side measured over one call."""

    frames_out: int = 0
    frames_held: int = 0  # written again because a frame packet never came
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
) -> ReceiverReport:
    """Join the call at ``host``, record the rebuilt frames to ``output`` until Bye.

    Frame i of the recording rebuilds the sender's frame i: a frame packet that never
    arrives is replaced by the previous picture, so the recording stays aligned.
    """
    report = ReceiverReport()
    with ReceiverEndpoint(host, pub_port, snapshot_port) as endpoint:
        snapshot = endpoint.fetch_snapshot(timeout_ms=int(join_timeout_s * 1000))
        decoder = FaceDecoder(snapshot)
        # Tell the sender we can keep up from now on (building the decoder takes ~0.5 s).
        endpoint.send_stats({"ready": 1.0})
        next_seq = snapshot.seq
        last: np.ndarray | None = None
        try:
            with Mp4Recorder(output, snapshot.width, snapshot.height, snapshot.fps) as recorder:
                while True:
                    packet = endpoint.recv(timeout_ms=200)
                    if packet is None:
                        if not endpoint.peer_alive:
                            report.ended_by = "peer lost"
                            break
                        continue
                    if isinstance(packet, Bye):
                        report.ended_by = "bye"
                        report.frames_held += _hold(recorder, last, packet.seq - next_seq)
                        break
                    if not isinstance(packet, Frame) or packet.seq < next_seq:
                        continue
                    start = time.perf_counter()
                    report.frames_held += _hold(recorder, last, packet.seq - next_seq)
                    try:
                        last = decoder.reconstruct(packet)
                    except ValueError as exc:
                        logger.debug("dropped frame %d: %s", packet.seq, exc)
                        report.malformed += 1
                        continue
                    report.latency_ms.append((now_us() - packet.capture_us) / 1000.0)
                    recorder.write(last)
                    report.busy_s += time.perf_counter() - start
                    next_seq = packet.seq + 1
                report.frames_out = recorder.frames
        finally:
            decoder.close()
        report.malformed += endpoint.stats.malformed
        report.bytes_received = dict(endpoint.bytes_received)
        report.bytes_sent = dict(endpoint.bytes_sent)
    return report


def _hold(recorder: Mp4Recorder, last: np.ndarray | None, count: int) -> int:
    """Write the previous picture ``count`` times (frames that never came)."""
    if last is None or count <= 0:
        return 0
    for _ in range(count):
        recorder.write(last)
    return count
