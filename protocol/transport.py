"""ZeroMQ transport: the ZeroMQ Guide's "Clone" pattern with a back channel.

The sender binds a PUB socket (updates: Frame, RemPatch, Heartbeat, Bye, and optionally a new
Snapshot) and a ROUTER socket (snapshot requests and the back channel: KeyframeRequest,
ReceiverStats, probes). A receiver connects a SUB and a DEALER socket.

Handshake (docs/protocol.md, "Joining"): the receiver subscribes first, then proves that its
subscription is live before it asks for the snapshot: it sends a Heartbeat probe over DEALER
every 100 ms, the sender answers each probe by publishing a Heartbeat, and as soon as the SUB
socket has anything to read (a Heartbeat or a Frame) the subscription is live. Only then does
the receiver send SnapshotRequest, so when the sender answers it, every packet it publishes
afterwards reaches that receiver. :meth:`SenderEndpoint.wait_for_receiver` waits for that
answer. Updates queued on SUB before the snapshot arrived stay queued; :meth:`recv` drops those
older than the snapshot's seq.

This is the only module that imports zmq.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import TracebackType
from typing import Self

import zmq

from protocol.constants import (
    CHANNEL_CONTROL,
    CHANNEL_SNAPSHOT,
    CHANNELS,
    HEARTBEAT_INTERVAL_S,
    HWM,
    MAX_PACKET_BYTES,
    PEER_TIMEOUT_S,
    PROBE_INTERVAL_MS,
)
from protocol.packets import (
    Bye,
    DeltaFrame,
    Heartbeat,
    KeyFrame,
    KeyframeRequest,
    Packet,
    PacketError,
    ReceiverStats,
    RemPatch,
    Snapshot,
    SnapshotRequest,
    decode,
)

logger = logging.getLogger(__name__)

#: Packets that travel on the PUB/SUB update channel.
UPDATE_KINDS = (KeyFrame, DeltaFrame, RemPatch, Heartbeat, Bye, Snapshot)
#: Most messages handled per call of SenderEndpoint.poll (bounds the time spent under flood).
_MAX_DRAIN = 1000


class TransportError(RuntimeError):
    """A transport-level failure: timeout during the handshake, misuse, closed endpoint."""


@dataclass
class TransportStats:
    """Packet counters of one endpoint."""

    received: int = 0  # well-formed packets accepted
    malformed: int = 0  # undecodable or unexpected packets, dropped
    dropped_old: int = 0  # updates older than the snapshot's seq, dropped


def _socket(context: zmq.Context[zmq.Socket[bytes]], kind: int) -> zmq.Socket[bytes]:
    sock = context.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.SNDHWM, HWM)
    sock.setsockopt(zmq.RCVHWM, HWM)
    # A peer that sends a message beyond the limit is disconnected by libzmq.
    sock.setsockopt(zmq.MAXMSGSIZE, MAX_PACKET_BYTES)
    sock.setsockopt(zmq.RECONNECT_IVL, 100)
    sock.setsockopt(zmq.RECONNECT_IVL_MAX, 5000)
    return sock


def _bind(sock: zmq.Socket[bytes], host: str, port: int) -> int:
    sock.bind(f"tcp://{host}:{port if port else '*'}")
    endpoint = sock.getsockopt(zmq.LAST_ENDPOINT)
    assert isinstance(endpoint, bytes)
    return int(endpoint.rsplit(b":", 1)[1])


def _ms(seconds: float) -> int:
    return max(0, int(seconds * 1000))


class _Endpoint:
    """Context handling and byte counters shared by both ends."""

    def __init__(
        self, context: zmq.Context[zmq.Socket[bytes]] | None, clock: Callable[[], float]
    ) -> None:
        self._own_context = context is None
        self._context: zmq.Context[zmq.Socket[bytes]] = (
            zmq.Context() if context is None else context
        )
        self._clock = clock
        self._sockets: list[zmq.Socket[bytes]] = []
        self._closed = False
        self.stats = TransportStats()
        #: Payload bytes per channel ("snapshot", "geometry", "rem", "control").
        self.bytes_sent: dict[str, int] = dict.fromkeys(CHANNELS, 0)
        self.bytes_received: dict[str, int] = dict.fromkeys(CHANNELS, 0)

    def now_us(self) -> int:
        """The endpoint's clock in integer microseconds (``sent_us`` of heartbeats)."""
        return round(self._clock() * 1_000_000)

    def _session_id(self) -> int:
        """The session this endpoint serves or joined (0 before a snapshot)."""
        snapshot = getattr(self, "snapshot", None) or getattr(self, "_snapshot", None)
        return snapshot.session_id if snapshot is not None else 0

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"{type(self).__name__} is closed")

    def _drop(self, data: bytes, reason: str) -> None:
        self.stats.malformed += 1
        logger.debug("dropped %d-byte message: %s", len(data), reason)

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self) -> None:
        """Close the sockets at once (linger 0) and the context if this endpoint made it."""
        if self._closed:
            return
        self._closed = True
        for sock in self._sockets:
            sock.close(linger=0)
        if self._own_context:
            self._context.term()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class SenderEndpoint(_Endpoint):
    """The sender's side: publishes updates, serves the snapshot, reads the back channel.

    ``pub_port`` / ``snapshot_port`` 0 pick free ports; :attr:`ports` tells which.
    ``clock`` (seconds, monotonic) times heartbeats and gives ``Heartbeat.sent_us``; the
    default ``time.monotonic`` is CLOCK_MONOTONIC, shared by all processes of one Linux host.
    """

    def __init__(
        self,
        bind_host: str = "127.0.0.1",
        pub_port: int = 0,
        snapshot_port: int = 0,
        context: zmq.Context[zmq.Socket[bytes]] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(context, clock)
        self._pub = _socket(self._context, zmq.PUB)
        self._router = _socket(self._context, zmq.ROUTER)
        self._sockets = [self._pub, self._router]
        try:
            self._ports = (
                _bind(self._pub, bind_host, pub_port),
                _bind(self._router, bind_host, snapshot_port),
            )
        except zmq.ZMQError as exc:
            self.close()
            raise TransportError(f"cannot bind on {bind_host}: {exc}") from exc
        self._snapshot: Snapshot | None = None
        self._snapshot_bytes = b""
        self._waiting: list[bytes] = []  # identities that asked before a snapshot was set
        self._inbox: deque[Packet] = deque()
        self._last_publish = clock()
        self._last_seq = 0
        self.snapshots_served = 0
        logger.info("sender: PUB and ROUTER on %s, ports %s", bind_host, self._ports)

    @property
    def ports(self) -> tuple[int, int]:
        """(pub_port, snapshot_port) actually bound."""
        return self._ports

    def set_snapshot(self, snapshot: Snapshot) -> None:
        """Make ``snapshot`` the one served to (re)joining receivers; answers waiting requests."""
        self._check_open()
        if not isinstance(snapshot, Snapshot):
            raise TypeError(f"expected Snapshot, got {type(snapshot).__name__}")
        self._snapshot = snapshot
        self._snapshot_bytes = bytes(snapshot)
        waiting, self._waiting = self._waiting, []
        for identity in waiting:
            self._serve(identity)

    def publish(
        self, packet: KeyFrame | DeltaFrame | RemPatch | Heartbeat | Bye | Snapshot
    ) -> None:
        """Publish an update to every subscribed receiver (never blocks; drops past the HWM)."""
        self._check_open()
        if not isinstance(packet, UPDATE_KINDS):
            raise TypeError(f"{type(packet).__name__} is not an update packet")
        data = bytes(packet)
        self._pub.send(data)
        self.bytes_sent[packet.CHANNEL] += len(data)
        self._last_publish = self._clock()
        if isinstance(packet, KeyFrame):
            self._last_seq = packet.seq

    def heartbeat_if_idle(self) -> bool:
        """Publish a Heartbeat if nothing was published for HEARTBEAT_INTERVAL_S; True if sent."""
        if self._clock() - self._last_publish < HEARTBEAT_INTERVAL_S:
            return False
        self.publish(Heartbeat(self._session_id(), self._last_seq, self.now_us()))
        return True

    def poll(self, timeout_ms: int = 0) -> list[Packet]:
        """Handle the back channel; return KeyframeRequest and ReceiverStats packets received.

        Waits up to ``timeout_ms`` for the first message. Snapshot requests and probes are
        answered here; malformed messages are counted in ``stats.malformed`` and dropped.
        """
        self._check_open()
        if not self._inbox:
            self._read_router(timeout_ms)
        self._read_router(0)
        out = list(self._inbox)
        self._inbox.clear()
        return out

    def wait_for_receiver(self, timeout_s: float) -> None:
        """Block until a receiver has fetched the snapshot (so its subscription is live).

        Returns at once if one already has. Back-channel packets that arrive meanwhile are kept
        for the next :meth:`poll`. Raises TransportError after ``timeout_s`` seconds.
        """
        self._check_open()
        deadline = time.monotonic() + timeout_s
        while self.snapshots_served == 0:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                hint = " (no snapshot set)" if self._snapshot is None else ""
                raise TransportError(
                    f"no receiver fetched the snapshot within {timeout_s:g} s{hint}"
                )
            self._read_router(max(1, _ms(remaining)))

    def _read_router(self, timeout_ms: int) -> None:
        if not self._router.poll(timeout_ms, zmq.POLLIN):
            return
        for _ in range(_MAX_DRAIN):
            try:
                frames = self._router.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                return
            self._handle(frames)

    def _handle(self, frames: list[bytes]) -> None:
        if len(frames) != 2:
            self._drop(b"".join(frames[1:]), f"{len(frames) - 1}-part message")
            return
        identity, data = frames
        try:
            packet = decode(data)
        except PacketError as exc:
            self._drop(data, str(exc))
            return
        if isinstance(packet, SnapshotRequest):
            self._accept(packet, data)
            if self._snapshot is None:
                self._waiting.append(identity)
            else:
                self._serve(identity)
        elif isinstance(packet, Heartbeat):
            self._accept(packet, data)
            self.publish(Heartbeat(self._session_id(), self._last_seq, self.now_us()))
        elif isinstance(packet, (KeyframeRequest, ReceiverStats)):
            self._accept(packet, data)
            self._inbox.append(packet)
        else:
            self._drop(data, f"unexpected {type(packet).__name__} on the back channel")

    def _accept(self, packet: Packet, data: bytes) -> None:
        self.stats.received += 1
        self.bytes_received[packet.CHANNEL] += len(data)

    def _serve(self, identity: bytes) -> None:
        self._router.send_multipart([identity, self._snapshot_bytes])
        self.bytes_sent[CHANNEL_SNAPSHOT] += len(self._snapshot_bytes)
        self.snapshots_served += 1
        logger.info("served the snapshot (%d bytes)", len(self._snapshot_bytes))


class ReceiverEndpoint(_Endpoint):
    """The receiver's side: subscribes, fetches the snapshot, receives updates.

    ``clock`` (seconds, monotonic) times peer liveness.
    """

    def __init__(
        self,
        host: str,
        pub_port: int,
        snapshot_port: int,
        context: zmq.Context[zmq.Socket[bytes]] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(context, clock)
        self._pub_address = f"tcp://{host}:{pub_port}"
        self._snapshot_address = f"tcp://{host}:{snapshot_port}"
        self._sub = _socket(self._context, zmq.SUB)
        self._dealer = _socket(self._context, zmq.DEALER)
        self._sockets = [self._sub, self._dealer]
        # Subscribe first (Clone pattern), then connect the request socket.
        self._sub.setsockopt(zmq.SUBSCRIBE, b"")
        self._sub.connect(self._pub_address)
        self._dealer.connect(self._snapshot_address)
        self.snapshot: Snapshot | None = None
        self._last_heard = clock()
        self._last_seq = 0
        self._bye = False

    @property
    def peer_alive(self) -> bool:
        """False after PEER_TIMEOUT_S without a well-formed packet, or after a Bye."""
        return not self._bye and self._clock() - self._last_heard < PEER_TIMEOUT_S

    def fetch_snapshot(self, timeout_ms: int = 5000) -> Snapshot:
        """Run the joining handshake and return the sender's Snapshot.

        Raises TransportError if the sender does not answer within ``timeout_ms``.
        """
        self._check_open()
        deadline = time.monotonic() + timeout_ms / 1000
        # 1. Prove the subscription is live: probe until SUB has something to read.
        while not self._sub.poll(0, zmq.POLLIN):
            remaining = _ms(deadline - time.monotonic())
            if remaining <= 0:
                raise TransportError(
                    f"no published packet from {self._pub_address} within {timeout_ms} ms "
                    "(is the sender running?)"
                )
            self._send(Heartbeat(self._session_id(), self._last_seq, self.now_us()))
            self._sub.poll(min(PROBE_INTERVAL_MS, remaining), zmq.POLLIN)
        # 2. Ask for the snapshot; updates keep queueing on SUB meanwhile.
        self._send(SnapshotRequest())
        while True:
            remaining = _ms(deadline - time.monotonic())
            if remaining <= 0 or not self._dealer.poll(remaining, zmq.POLLIN):
                raise TransportError(
                    f"no snapshot from {self._snapshot_address} within {timeout_ms} ms"
                )
            data = self._dealer.recv()
            try:
                packet = decode(data)
            except PacketError as exc:
                self._drop(data, str(exc))
                continue
            if not isinstance(packet, Snapshot):
                self._drop(data, f"unexpected {type(packet).__name__} on the snapshot channel")
                continue
            self._take_snapshot(packet, data)
            logger.info("snapshot: session %d from seq %d", packet.session_id, packet.seq)
            return packet

    def recv(self, timeout_ms: int = 0) -> Packet | None:
        """The next update at or after the snapshot's seq, or None after ``timeout_ms``.

        Returns Frame, RemPatch, Heartbeat, Bye or a new Snapshot. Malformed messages are
        counted in ``stats.malformed`` and dropped; this never raises because of bad input.
        """
        self._check_open()
        if self.snapshot is None:
            raise TransportError("call fetch_snapshot() before recv()")
        deadline = time.monotonic() + timeout_ms / 1000
        while self._sub.poll(_ms(deadline - time.monotonic()), zmq.POLLIN):
            try:
                frames = self._sub.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                continue
            packet = self._update(frames)
            if packet is not None:
                return packet
        return None

    def request_keyframe(self, seq: int) -> None:
        """Ask the sender for a keyframe; ``seq`` is the last frame decoded."""
        self._send(KeyframeRequest(seq))

    def send_stats(self, values: Mapping[str, float]) -> None:
        """Send named statistics (finite floats) to the sender."""
        self._send(ReceiverStats(values))

    def _send(self, packet: Packet) -> None:
        self._check_open()
        data = bytes(packet)
        try:
            self._dealer.send(data, zmq.NOBLOCK)
        except zmq.Again:
            logger.debug("back channel full, dropped %s", type(packet).__name__)
            return
        self.bytes_sent[CHANNEL_CONTROL] += len(data)

    def _take_snapshot(self, snapshot: Snapshot, data: bytes) -> None:
        self.snapshot = snapshot
        self.stats.received += 1
        self.bytes_received[snapshot.CHANNEL] += len(data)
        self._last_heard = self._clock()

    def _update(self, frames: list[bytes]) -> Packet | None:
        data = frames[0] if len(frames) == 1 else b"".join(frames)
        if len(frames) != 1:
            self._drop(data, f"{len(frames)}-part message")
            return None
        try:
            packet = decode(data)
        except PacketError as exc:
            self._drop(data, str(exc))
            return None
        if not isinstance(packet, UPDATE_KINDS):
            self._drop(data, f"unexpected {type(packet).__name__} on the update channel")
            return None
        if isinstance(packet, Snapshot):
            self._take_snapshot(packet, data)
            return packet
        self._last_heard = self._clock()
        self._bye = isinstance(packet, Bye)
        assert self.snapshot is not None
        if isinstance(packet, (KeyFrame, RemPatch)) and packet.seq < self.snapshot.seq:
            self.stats.dropped_old += 1
            return None
        if isinstance(packet, KeyFrame):
            self._last_seq = packet.seq
        self.stats.received += 1
        self.bytes_received[packet.CHANNEL] += len(data)
        return packet
