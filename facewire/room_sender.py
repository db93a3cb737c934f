"""A room participant's own stream: the two-party sender's loop (sender/session.run_sender)
publishing to the room instead of to one receiver.

:class:`RoomSender` is the endpoint ``run_sender`` publishes to: the packets go into the
media path's :class:`~facewire.protocol.media_path.Bundler`, as on a two-party call's datagram path,
and each bundle leaves as one sealed NATS message on ``fw.ROOM.m.NAME``. The snapshot goes
to the room's KV bucket once, where late joiners read it. Keyframe requests come from the
receiving side (which opens the control messages) through :meth:`request_keyframe`.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence

from facewire.protocol import subjects
from facewire.protocol.clock import now_us
from facewire.protocol.constants import HEARTBEAT_INTERVAL_S
from facewire.protocol.media_path import DATAGRAM_COST, Bundler
from facewire.protocol.packets import (
    Bye,
    DeltaFrame,
    Heartbeat,
    KeyFrame,
    KeyframeRequest,
    Packet,
    Refresh,
    RemPatch,
    Snapshot,
)
from facewire.protocol.sender_keys import SenderKeys
from facewire.protocol.sframe import RoomKey, Sealer
from facewire.room_link import RoomLink

logger = logging.getLogger(__name__)

#: A REM patch this large waits for the budget (a paced one); a smaller one goes with its frame.
PACED_PATCH_BYTES = 64
SNAPSHOT = b"s"
MEDIA = b"m"


class RoomSender:
    """The endpoint ``run_sender`` drives (the part of SenderEndpoint's interface it uses)."""

    def __init__(
        self,
        link: RoomLink,
        key: RoomKey | SenderKeys,
        name: str,
        sealer: Sealer,
        fps: float,
        max_bps: float,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.link = link
        self.key = key
        self.name = name
        self.sealer = sealer
        self.max_bps = max_bps
        self._clock = clock
        self._bundler = Bundler(fps)
        self._lock = threading.Lock()  # a microphone's thread publishes sound too
        self._requests: deque[KeyframeRequest] = deque()
        self._subject = subjects.media(key.room, name)
        self._metadata = key.metadata(name, MEDIA)
        self._session_id = 0
        self._last_seq = 0
        self._last_publish = clock()
        #: Snapshots served to receivers that asked (none: the peers read them from the bucket).
        self.snapshots_served = 0
        self.bundles = 0
        self.bytes_sealed = 0
        self.bytes_by_kind: Counter[str] = Counter()
        self.started = clock()

    def set_snapshot(
        self, snapshot: Snapshot, draft: Snapshot | None = None, sharper: Sequence[Snapshot] = ()
    ) -> None:
        """Put ``snapshot`` in the room's bucket, sealed (``draft`` and ``sharper`` are not
        needed: the relay keeps the whole snapshot and a joiner reads it at the relay's
        speed)."""
        self._session_id = snapshot.session_id
        sealed = self.sealer.seal(bytes(snapshot), self.key.metadata(self.name, SNAPSHOT))
        self.link.put_snapshot(sealed)
        self.bytes_by_kind["snapshot"] += len(sealed)

    def publish(self, packet: Packet, seq: int | None = None) -> None:
        data = bytes(packet)
        with self._lock:
            self.bytes_by_kind[type(packet).__name__] += len(data)
            self._last_publish = self._clock()
            if isinstance(packet, (RemPatch, Refresh)) and (
                len(data) >= PACED_PATCH_BYTES or self._bundler.patch_bytes_waiting
            ):
                self._bundler.add_patch(data)
            else:
                self._bundler.add(data)
            if isinstance(packet, KeyFrame):
                self._last_seq = packet.seq
            elif isinstance(packet, DeltaFrame) and seq is not None:
                self._last_seq = seq
            if isinstance(packet, Bye):
                # What waits for the budget goes first; nothing is taken after the Bye.
                while self._bundler.patch_bytes_waiting:
                    self._send_all(self._bundler.flush(self._clock(), math.inf))
            if isinstance(packet, (KeyFrame, Bye, Heartbeat)):
                # A keyframe is what a joiner waits for; a Bye and a heartbeat stand alone.
                self._send_all(self._bundler.flush(self._clock(), math.inf))

    def end_frame(self) -> None:
        with self._lock:
            now = self._clock()
            self._send_all(self._bundler.end_frame(now, self.max_bps))

    def _send_all(self, bundles: list[bytes]) -> None:
        for bundle in bundles:
            sealed = self.sealer.seal(bundle, self._metadata)
            self.link.publish(self._subject, sealed)
            self.bundles += 1
            self.bytes_sealed += len(sealed)

    def heartbeat_if_idle(self) -> bool:
        if self._clock() - self._last_publish < HEARTBEAT_INTERVAL_S:
            return False
        self.heartbeat()
        return True

    def heartbeat(self) -> None:
        """A Heartbeat now (``run_sender`` says a new scene's session with one)."""
        self.publish(Heartbeat(self._session_id, self._last_seq, now_us()))

    def patch_budget_bps(self) -> float:
        headers = DATAGRAM_COST * 8 * self._bundler.fps / self._bundler.k
        return max(0.0, self.max_bps - headers - self._bundler.due_bps)

    def request_keyframe(self, request: KeyframeRequest) -> None:
        """A receiver asked (called from the receiving side's thread)."""
        self._requests.append(request)

    def reconnected(self) -> None:
        """The link is back, through another node (called from its thread): what it sent to
        the node that died may be lost, so the next frame is a keyframe without waiting for
        a receiver to find its chain broken and ask."""
        self._requests.append(KeyframeRequest(min(self._last_seq, 2**32 - 1)))

    def poll(self, timeout_ms: int = 0) -> list[Packet]:
        out: list[Packet] = []
        while self._requests:
            out.append(self._requests.popleft())
        return out

    def figures(self) -> dict[str, object]:
        elapsed = max(1e-9, self._clock() - self.started)
        return {
            "bundles": self.bundles,
            "bytes_sealed": self.bytes_sealed,
            "kbps_sealed": round(self.bytes_sealed * 8 / elapsed / 1000, 2),
            "bytes_by_kind": dict(self.bytes_by_kind),
            "frames_per_bundle": self._bundler.k,
        }
