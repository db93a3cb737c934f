"""ZeroMQ transport: the ZeroMQ Guide's "Clone" pattern with a back channel, over CURVE.

The sender has a PUB socket (updates: KeyFrame, DeltaFrame, RemPatch, Refresh, AudioFrame,
Heartbeat, Bye, and a new Snapshot) and a ROUTER socket (snapshot requests and the back
channel: KeyframeRequest, ReceiverStats, probes); a receiver has a SUB and a DEALER socket.
By default the sender binds and the receiver connects; either side may take the other role
(``SenderEndpoint(connect=True)`` with ``ReceiverEndpoint(bind=True)``), which changes nothing
above the sockets: the sender stays the CURVE server, the subscription and the handshake run
the same way.

Security: by default every socket uses CURVE. The sender's PUB and ROUTER are CURVE servers with
the sender's secret key, and a ZAP handler admits only the clients whose public keys it was
given (``allowed_keys``); the receiver's SUB and DEALER are CURVE clients that know the sender's
public key, so an impostor that binds the sender's ports cannot complete a handshake with them.
Unencrypted sockets must be asked for with ``plain=True``. Key files: :mod:`facewire.protocol.keys`.

Handshake (docs/protocol.md, "Joining"): the receiver subscribes first, then proves that its
subscription is live before it asks for the snapshot: it sends a Heartbeat probe over DEALER
every 100 ms, the sender answers probes by publishing a Heartbeat (at most one per 100 ms in
total, however many probes come), and as soon as the SUB socket has anything to read the
subscription is live. Only then does the receiver send SnapshotRequest (repeated every second
until answered), so when the sender answers it, every packet it publishes afterwards reaches
that receiver. :meth:`SenderEndpoint.wait_for_receiver` waits for that answer. Updates queued on
SUB before the snapshot arrived stay queued; :meth:`ReceiverEndpoint.recv` drops those older
than the snapshot's seq.

Bounded memory: every queue is small (constants ``UPDATE_HWM``, ``BACK_CHANNEL_HWM``,
``SNAPSHOT_HWM``). A receiver that stops reading makes libzmq drop what the sender publishes to
it, so the sender's memory stays flat; it sees a gap in seq. Each peer is sent at most one
snapshot per ``SNAPSHOT_MIN_INTERVAL_S``, and replies it has not read are dropped, not queued.

The second path: TCP turns a lost segment into delay for every message behind it, so on a lossy
link some frames come a round trip or more late. A receiver that sees late frames says so
(ReceiverStats ``late_frames``); for SPARE_PATH_HOLD_S after its last such report the sender also
sends it every KeyFrame and DeltaFrame over the ROUTER/DEALER connection, whose losses are
independent of the PUB connection's. :meth:`ReceiverEndpoint.recv` passes on whichever copy of
a frame packet comes first (by its counter) and drops the other.

Rejoining: when the session's SUB connection drops and comes back (the sender restarted, or the
network failed), or it names another session (``session_id``), :meth:`recv` raises
:class:`RejoinNeeded` until :meth:`ReceiverEndpoint.fetch_snapshot` is called again. Packets by
any other connection (a bound receiver takes anyone's), or naming another session by any other
way, are ignored and counted (docs/protocol.md 3.8): a stranger cannot switch or end a session.

This is the only module that imports zmq.
"""

from __future__ import annotations

import dataclasses
import errno
import itertools
import logging
import math
import os
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Self, TypeVar

import zmq
from zmq.utils.monitor import recv_monitor_message

from facewire.protocol.bundle import MAX_REASSEMBLED
from facewire.protocol.channels import COUNTER_MOD
from facewire.protocol.clock import now_us
from facewire.protocol.constants import (
    BACK_CHANNEL_HWM,
    CHANNEL_CONTROL,
    CHANNEL_SNAPSHOT,
    CHANNEL_SPARE,
    CHANNELS,
    COPY_WINDOW_S,
    DRAFT_ABOVE_S,
    DRAFT_PATH_WAIT_S,
    FAST_JOIN_BPS,
    HEARTBEAT_INTERVAL_S,
    LATE_FRAME_MS,
    LATE_FRAMES,
    LATE_REPORT_S,
    MAX_PACKET_BYTES,
    MAX_SEQ_STEP,
    MAX_SNAPSHOT_PEERS,
    MAX_UPDATE_BYTES,
    PEER_TIMEOUT_S,
    PROBE_INTERVAL_MS,
    REFINE_ATTEMPTS,
    REFINE_RETRY_S,
    REFINED,
    SNAPSHOT_HWM,
    SNAPSHOT_MIN_INTERVAL_S,
    SNAPSHOT_MS,
    SNAPSHOT_RETRY_MS,
    SNAPSHOT_TRANSFER_ROOM,
    SPARE_PATH_HOLD_S,
    UINT32_MAX,
    UPDATE_HWM,
    ZAP_DOMAIN,
)
from facewire.protocol.hostile import Refusals
from facewire.protocol.keys import KeyPair, load_keypair, load_public_key, load_public_keys
from facewire.protocol.media_path import (
    DATAGRAM_COST,
    DEFAULT_BUDGET_BPS,
    HELLO_INTERVAL_S,
    HURRIED_REPORT_INTERVAL_S,
    Bundler,
    ReceiverMediaPath,
    SenderMediaPath,
    WireCounts,
    fragments,
)
from facewire.protocol.packets import (
    AudioFrame,
    Bye,
    DeltaFrame,
    Heartbeat,
    KeyFrame,
    KeyframeRequest,
    Kind,
    MediaKey,
    Packet,
    PacketError,
    ReceiverStats,
    Refresh,
    RemPatch,
    Snapshot,
    SnapshotRequest,
    decode,
    header_byte,
)

logger = logging.getLogger(__name__)

KeyFile = str | os.PathLike[str]

#: Updates with a seq, dropped by the receiver when older than the snapshot's seq. (A DeltaFrame
#: has no seq: it is passed on, and the decoder ignores deltas until its chain starts.)
SEQ_KINDS = (KeyFrame, RemPatch, Refresh)
#: Packets that travel on the PUB/SUB update channel.
UPDATE_KINDS = (KeyFrame, DeltaFrame, RemPatch, Refresh, Heartbeat, Bye, Snapshot, AudioFrame)
#: Packets that may also come over the second path (ROUTER to DEALER).
FRAME_KINDS = (KeyFrame, DeltaFrame)
#: Updates that travel as datagrams while a receiver's media path is live (a Snapshot never does).
MEDIA_KINDS = (KeyFrame, DeltaFrame, RemPatch, Refresh, Heartbeat, Bye, AudioFrame)
#: Patches (REM and refresh) wait for what the budget leaves when at least this long (else
#: they ride with their frame).
PATCH_KINDS = (RemPatch, Refresh)
_PACED_PATCH_BYTES = 64
#: Most datagrams sent at once to empty the queue of patches before a Bye.
_MAX_DRAIN_DATAGRAMS = 64
#: Updates remembered to drop the second of two copies that came by both paths.
_RECENT_UPDATES = 512
_SNAPSHOT_BYTE = bytes([header_byte(Kind.SNAPSHOT)])
#: Most messages handled per call of SenderEndpoint.poll (bounds the time spent under flood).
_MAX_DRAIN = 1000
_HANDSHAKE_FAILED = (
    zmq.EVENT_HANDSHAKE_FAILED_NO_DETAIL
    | zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL
    | zmq.EVENT_HANDSHAKE_FAILED_AUTH
)
_zap_suffix = itertools.count(1)
_M = TypeVar("_M", SenderMediaPath, ReceiverMediaPath)


class TransportError(RuntimeError):
    """A transport-level failure: timeout during the handshake, misuse, closed endpoint."""


class RejoinNeeded(TransportError):
    """The update stream no longer belongs to the snapshot: call fetch_snapshot() again.

    ``session``: the session the stream's packets now name, where that is what changed (a
    restarted sender, or a new scene of the call: its snapshot says which); None when the
    connection dropped and came back.
    """

    def __init__(self, reason: str, session: int | None = None) -> None:
        super().__init__(reason)
        self.session = session


@dataclass
class TransportStats:
    """Packet counters of one endpoint."""

    received: int = 0  # well-formed packets accepted
    malformed: int = 0  # undecodable or unexpected packets, dropped
    dropped_old: int = 0  # updates older than the snapshot's seq, dropped
    # The second path (receiver): frames reported late, second copies dropped, and of those the
    # ones that came LATE_FRAME_MS or more after the first, in all and when the first copy was
    # the second path's (a frame the second path brought that much sooner).
    late_frames: int = 0
    copies: int = 0
    late_copies: int = 0
    saved: int = 0
    # The media path: updates that came both as datagrams and on SUB, the second dropped.
    duplicates: int = 0
    # Updates of another session, or by another connection than the session's, ignored (3.8).
    ignored_sessions: int = 0


def _socket(
    context: zmq.Context[zmq.Socket[bytes]], kind: int, sndhwm: int, rcvhwm: int
) -> zmq.Socket[bytes]:
    sock = context.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.SNDHWM, sndhwm)
    sock.setsockopt(zmq.RCVHWM, rcvhwm)
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


def _attach(
    sockets: list[zmq.Socket[bytes]], host: str, ports: tuple[int, int], bind: bool, side: str
) -> tuple[int, int]:
    """Bind (port 0: any free port) or connect each socket to its port; the ports used.

    A connect names a peer: it needs real ports, and libzmq only checks the host later (an
    unknown host just never answers), so both are checked here.
    """
    if bind:
        try:
            return (_bind(sockets[0], host, ports[0]), _bind(sockets[1], host, ports[1]))
        except zmq.ZMQError as exc:
            # libzmq's text ends with "(addr='tcp://...')", which the line says already.
            reason = os.strerror(exc.errno) if exc.errno else str(exc)
            raise TransportError(f"{side}: cannot bind on {host} ports {ports}: {reason}") from exc
    for port in ports:
        if not 1 <= port <= 65535:
            raise TransportError(f"{side}: cannot connect to port {port} (expected 1..65535)")
    for sock, port in zip(sockets, ports, strict=True):
        try:
            sock.connect(f"tcp://{host}:{port}")
        except zmq.ZMQError as exc:
            raise TransportError(f"{side}: cannot connect to {host}:{port}: {exc}") from exc
    return ports


def _open_media(kind: type[_M], host: str, port: int, bind: bool, wanted: bool) -> _M | None:
    """The UDP media path on ``host:port``, or None (not wanted, or no UDP socket there: the
    media then go by ZeroMQ, which the log says)."""
    if not wanted:
        return None
    try:
        return kind(host, port, bind)
    except OSError as exc:
        logger.warning("media: no UDP socket on %s:%d (%s): media over ZeroMQ/TCP", host, port, exc)
        return None


def _ms(seconds: float) -> int:
    return max(0, int(seconds * 1000))


class _Zap:
    """The ZAP handler of one context (libzmq allows one), shared by its CURVE senders.

    Each sender registers its own ZAP domain with the public keys it admits.
    """

    _lock = threading.Lock()
    _by_context: dict[int, _Zap] = {}

    def __init__(self, context: zmq.Context[zmq.Socket[bytes]]) -> None:
        from zmq.auth.thread import ThreadAuthenticator

        self.allowed: dict[str, frozenset[bytes]] = {}
        self._auth = ThreadAuthenticator(context, log=logging.getLogger(f"{__name__}.zap"))
        try:
            self._auth.start()
        except zmq.ZMQError as exc:
            if self._auth.zap_socket is not None:
                self._auth.zap_socket.close(linger=0)
            raise TransportError(f"cannot start the ZAP handler: {exc}") from exc

    def callback(self, domain: str, key: bytes) -> bool:
        """ZAP: may the client with this public key (Z85) connect to ``domain``?"""
        allowed = key in self.allowed.get(domain, frozenset())
        if not allowed:
            logger.info("refused a CURVE client with key %s (not allowed)", key.decode())
        return allowed

    @classmethod
    def register(
        cls, context: zmq.Context[zmq.Socket[bytes]], domain: str, keys: frozenset[bytes]
    ) -> None:
        with cls._lock:
            zap = cls._by_context.get(id(context))
            if zap is None:
                zap = cls._by_context[id(context)] = _Zap(context)
            zap.allowed[domain] = keys
            zap._auth.configure_curve_callback(domain, credentials_provider=zap)

    @classmethod
    def unregister(cls, context: zmq.Context[zmq.Socket[bytes]], domain: str) -> None:
        with cls._lock:
            zap = cls._by_context.get(id(context))
            if zap is None:
                return
            zap.allowed.pop(domain, None)
            zap._auth.credentials_providers.pop(domain, None)
            if not zap.allowed:
                zap._auth.stop()
                del cls._by_context[id(context)]


def _check_mode(plain: bool, has_keys: bool, side: str, names: str) -> None:
    if plain and has_keys:
        raise TransportError(f"{side}: plain=True and key files exclude each other")
    if not plain and not has_keys:
        raise TransportError(
            f"{side}: no CURVE keys ({names}); pass keys or plain=True for an unencrypted call"
        )


class _Endpoint:
    """Context handling and byte counters shared by both ends."""

    _media: SenderMediaPath | ReceiverMediaPath | None = None

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
        #: The same messages by size, per channel: {bytes: messages} (the wire overhead of
        #: ZeroMQ framing and TCP/IP headers is paid per message).
        self.sizes_sent: dict[str, Counter[int]] = {ch: Counter() for ch in CHANNELS}
        self.sizes_received: dict[str, Counter[int]] = {ch: Counter() for ch in CHANNELS}

    def media_figures(self) -> dict[str, object]:
        """The media path's counts for the stats: datagrams and wire bytes each way, drops."""
        if self._media is None:
            return {"udp": False}
        return {"udp": True, **dataclasses.asdict(self._media.counts), **self._media_extra()}

    def _media_extra(self) -> dict[str, object]:
        return {}

    def now_us(self) -> int:
        """The endpoint's clock in integer microseconds (``sent_us`` of heartbeats)."""
        return round(self._clock() * 1_000_000)

    def _check_open(self) -> None:
        if self._closed:
            raise TransportError(f"{type(self).__name__} is closed")

    def _accept(self, packet: Packet, data: bytes) -> None:
        """Count a well-formed packet received."""
        self.stats.received += 1
        self.bytes_received[packet.CHANNEL] += len(data)
        self.sizes_received[packet.CHANNEL][len(data)] += 1

    def _accept_sent(self, packet: Packet, data: bytes) -> None:
        """Count a packet sent (its payload bytes, whichever path it takes)."""
        self.bytes_sent[packet.CHANNEL] += len(data)
        self.sizes_sent[packet.CHANNEL][len(data)] += 1

    def _drop(self, data: bytes, reason: str) -> None:
        self.stats.malformed += 1
        logger.debug("dropped %d-byte message: %s", len(data), reason)

    def _release(self) -> None:
        """Free what the subclass holds besides its sockets (before the context ends)."""

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self, linger_s: float = 0.0) -> None:
        """Close the sockets and the context if this endpoint made it.

        By default at once (linger 0: what is still queued is dropped). ``linger_s`` > 0 gives
        the last messages (a Bye) that long to leave; the close waits for them, at most that.
        """
        if self._closed:
            return
        self._closed = True
        for sock in self._sockets:
            sock.close(linger=_ms(linger_s))
        self._release()
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


#: The pictures' share of what the budget leaves while the snapshot's full images are on their
#: way (they go after the pictures): at 24 kbit/s the pictures keep their own budgets, at 16
#: they give up some of them.
PATCH_SHARE_REFINING = 0.5


class SenderEndpoint(_Endpoint):
    """The sender's side: publishes updates, serves the snapshot, reads the back channel.

    ``pub_port`` / ``snapshot_port`` 0 pick free ports; :attr:`ports` tells which.
    ``clock`` (seconds, monotonic) times heartbeats and gives ``Heartbeat.sent_us``; the
    default ``time.monotonic`` is CLOCK_MONOTONIC, shared by all processes of one Linux host.

    ``secret_key_file`` is the sender's ``.key_secret`` file; ``allowed_keys`` is a directory
    of the receivers' public ``.key`` files, or a list of such files. Without them, pass
    ``plain=True`` for unencrypted, unauthenticated sockets.

    ``connect=True`` connects both sockets to a receiver that binds (``bind_host`` is then the
    receiver's host and both ports must be given); the sender is still the CURVE server.
    """

    def __init__(
        self,
        bind_host: str = "127.0.0.1",
        pub_port: int = 0,
        snapshot_port: int = 0,
        context: zmq.Context[zmq.Socket[bytes]] | None = None,
        clock: Callable[[], float] = time.monotonic,
        *,
        secret_key_file: KeyFile | None = None,
        allowed_keys: KeyFile | Iterable[KeyFile] | None = None,
        plain: bool = False,
        connect: bool = False,
        udp: bool = True,
        max_bps: float | None = None,
        fps: float = 30.0,
    ) -> None:
        has_keys = secret_key_file is not None or allowed_keys is not None
        _check_mode(plain, has_keys, "sender", "secret_key_file, allowed_keys")
        keys: KeyPair | None = None
        allowed: frozenset[bytes] = frozenset()
        if not plain:
            if secret_key_file is None or allowed_keys is None:
                raise TransportError("sender: CURVE needs both secret_key_file and allowed_keys")
            keys = load_keypair(secret_key_file)
            allowed = load_public_keys(allowed_keys)
        super().__init__(context, clock)
        self._zap_domain = ""
        self._pub = _socket(self._context, zmq.PUB, UPDATE_HWM, UPDATE_HWM)
        self._router = _socket(self._context, zmq.ROUTER, SNAPSHOT_HWM, BACK_CHANNEL_HWM)
        # Unread replies raise Again (counted and dropped) instead of vanishing silently.
        self._router.setsockopt(zmq.ROUTER_MANDATORY, 1)
        self._sockets = [self._pub, self._router]
        self._media: SenderMediaPath | None = None
        try:
            if keys is not None:
                self._zap_domain = f"{ZAP_DOMAIN}.{os.getpid()}.{next(_zap_suffix)}"
                _Zap.register(self._context, self._zap_domain, allowed)
                for sock in self._sockets:
                    sock.setsockopt(zmq.CURVE_SERVER, 1)
                    sock.setsockopt(zmq.CURVE_SECRETKEY, keys.secret)
                    sock.setsockopt(zmq.CURVE_PUBLICKEY, keys.public)
                    sock.setsockopt(zmq.ZAP_DOMAIN, self._zap_domain.encode())
            self._ports = _attach(
                [self._pub, self._router],
                bind_host,
                (pub_port, snapshot_port),
                bind=not connect,
                side="sender",
            )
            self._media = _open_media(SenderMediaPath, bind_host, self._ports[0], not connect, udp)
        except BaseException:
            self.close()
            raise
        self._bundler = Bundler(fps)
        self._paced = False
        #: The on-the-wire budget of this direction, bits per second (headers counted).
        self.max_bps = DEFAULT_BUDGET_BPS if max_bps is None else max_bps
        self._snapshot: Snapshot | None = None
        self._snapshot_bytes = b""
        # What the datagrams carry after a draft, in order: the last is the full snapshot.
        self._sharper: list[bytes] = []
        self._waiting: dict[bytes, None] = {}  # identities that asked before a snapshot was set
        self._served_at: dict[bytes, float] = {}  # identity -> time.monotonic() of the last reply
        # identity -> the snapshot version it was sent, and that reply's size (the draft's or
        # the full one's: its transfer time measures the link, docs/protocol.md 8.6)
        self._served_what: dict[bytes, tuple[int, int]] = {}
        self._snapshot_version = 0
        self._draft_bytes = b""
        # identity -> (when the full snapshot may go (again), attempts left) after a draft
        self._refine: dict[bytes, tuple[float, int]] = {}
        # identity -> (when it goes on ROUTER instead, the draft): drafts that go in the
        # datagrams once their receiver's path is open (docs/protocol.md 8.7)
        self._draft_waits: dict[bytes, tuple[float, bytes]] = {}
        # Receivers whose draft went in the datagrams: a request again soon means one was lost.
        self._draft_by_datagram: set[bytes] = set()
        # ... and those it went to again: how long it took says nothing of their link.
        self._draft_resent: set[bytes] = set()
        # Receivers whose draft came fast: a later snapshot (a new scene's) goes to them whole.
        self._fast: set[bytes] = set()
        self.refinements_sent = 0
        self._inbox: deque[Packet] = deque()
        self._last_publish = clock()
        self._last_probe_answer = -math.inf
        self._last_seq = 0
        self._spare_until: dict[bytes, float] = {}  # identity -> time.monotonic() it ends
        self.snapshots_served = 0
        #: Second copies of frame packets not sent: the peer's ROUTER queue was full.
        self.spare_dropped = 0
        #: Snapshot requests not answered: rate limit, too many peers, or replies left unread.
        self.snapshots_refused = 0
        #: Probes not answered because a Heartbeat was published for a probe less than
        #: PROBE_INTERVAL_MS ago.
        self.probes_unanswered = 0
        mode = "plain" if plain else f"CURVE, {len(allowed)} allowed keys"
        how = "connected to" if connect else "bound on"
        logger.info(
            "sender: PUB and ROUTER %s %s, ports %s (%s)", how, bind_host, self._ports, mode
        )

    @property
    def ports(self) -> tuple[int, int]:
        """(pub_port, snapshot_port) bound, or connected to."""
        return self._ports

    def _release(self) -> None:
        if self._zap_domain:
            _Zap.unregister(self._context, self._zap_domain)
        if self._media is not None:
            self._media.close()

    @property
    def wire(self) -> WireCounts | None:
        """The media path's datagrams and their bytes on the wire (None without one)."""
        return None if self._media is None else self._media.counts

    def budget_bps(self) -> float:
        """This direction's budget: ``max_bps``, or what a receiver's link carries if less."""
        if self._media is None:
            return self.max_bps
        return self._media.budget_bps(self._clock(), self.max_bps)

    def patch_budget_bps(self) -> float:
        """What the budget leaves for REM patches, bits per second (payload): while the
        snapshot's full images cross (behind the patches), at most PATCH_SHARE_REFINING of
        it, so that they cross too."""
        budget = self.budget_bps()
        headers = self._bundler.header_bytes * 8 * self._bundler.fps / self._bundler.k
        left = max(0.0, budget - headers - self._bundler.due_bps)
        return left * PATCH_SHARE_REFINING if self._bundler.bulk_bytes_waiting else left

    @property
    def frames_per_datagram(self) -> int:
        return self._bundler.k

    def _media_extra(self) -> dict[str, object]:
        assert self._media is not None
        peers = self._media.live(self._clock())
        last = peers[0].controller.last if peers else None
        return {
            "receivers_on_udp": len(peers),
            "frames_per_datagram": self._bundler.k,
            "budget_kbps": self.budget_bps() / 1000,
            # the rate control's estimate of the thinnest receiver's link
            "rate_kbps": min((p.controller.rate_bps / 1000 for p in peers), default=None),
            "rate_decreases": sum(p.controller.decreases for p in peers),
            "redundant": self._bundler.redundant,
            "queue_ms": None if last is None else last.queue_ms,
            "loss": None if last is None else last.loss,
        }

    def _on_udp(self, now: float) -> bool:
        return self._media is not None and bool(self._media.live(now))

    def end_frame(self) -> None:
        """A frame's updates are all published: send the datagram if one is due.

        A caller that marks its frames' ends this way has its updates bundled, one datagram for
        every ``frames_per_datagram`` frames; until the first call each update leaves alone.
        """
        self._check_open()
        self._paced = True
        if self._media is None:
            return
        now = self._clock()
        self._read_media(now)
        self._send_drafts(now)
        live = self._media.live(now)
        self._bundler.redundant = any(p.controller.lossy for p in live)
        self._bundler.losing = any(p.controller.losing for p in live)
        self._bundler.hurry = any(p.controller.wants_reports(now) for p in live)
        if self._refine:
            self._send_refinements(now)
        # No headers to count on this machine: one frame a datagram there (frames_per_datagram).
        self._bundler.header_bytes = 0 if self._media.on_this_machine(now) else DATAGRAM_COST
        packing = self._media.budget_bps(now, self.max_bps, congested_only=True)
        for bundle in self._bundler.end_frame(now, self.budget_bps(), packing):
            self._media.send(bundle, now)

    def set_snapshot(
        self,
        snapshot: Snapshot,
        draft: Snapshot | None = None,
        sharper: Sequence[Snapshot] = (),
    ) -> None:
        """Make ``snapshot`` the one served to (re)joining receivers; answers waiting requests.

        ``draft``: its first, small version (sender/snapshot_draft.py), served instead where the
        full one would take more than DRAFT_ABOVE_S at the budget; the full one then follows
        paced behind the media (docs/protocol.md 8.7), as ``sharper`` where given: versions
        that the datagrams carry in turn (at most MAX_REASSEMBLED bytes each), the last the
        full snapshot as they can carry it.
        """
        self._check_open()
        if not isinstance(snapshot, Snapshot):
            raise TypeError(f"expected Snapshot, got {type(snapshot).__name__}")
        self._snapshot = snapshot
        self._snapshot_bytes = bytes(snapshot)
        self._sharper = [bytes(s) for s in sharper] or [self._snapshot_bytes]
        self._draft_bytes = b"" if draft is None else bytes(draft)
        self._refine.clear()
        self._snapshot_version += 1
        waiting, self._waiting = self._waiting, {}
        for identity in waiting:
            self._serve(identity, time.monotonic())

    def publish(
        self,
        packet: Packet,
        seq: int | None = None,
    ) -> None:
        """Publish an update to every subscribed receiver (never blocks; drops past the HWM).

        ``seq`` is the frame number of a DeltaFrame (it carries none; a KeyFrame's is its
        own): heartbeats then tell the last frame published, whichever kind it came in.
        """
        self._check_open()
        if not isinstance(packet, UPDATE_KINDS):
            raise TypeError(f"{type(packet).__name__} is not an update packet")
        if seq is not None and not 0 <= seq <= UINT32_MAX:
            raise ValueError(f"frame number {seq} outside [0, {UINT32_MAX}]")
        data = bytes(packet)
        now = self._clock()
        self._accept_sent(packet, data)
        self._last_publish = now
        on_udp = self._on_udp(now) and isinstance(packet, MEDIA_KINDS)
        if on_udp:
            self._bundle(packet, data, now)
        if not on_udp or isinstance(packet, Bye) or self._media_fallback(now):
            self._pub_send(data)
            if isinstance(packet, FRAME_KINDS) and self._spare_until:
                self._send_spare(data)
        if isinstance(packet, KeyFrame):
            self._last_seq = packet.seq
        elif isinstance(packet, DeltaFrame) and seq is not None:
            self._last_seq = seq

    def _read_media(self, now: float) -> None:
        """The receivers' datagrams: reports to the rate control, keyframe requests to the
        back channel's inbox."""
        assert self._media is not None
        self._media.read(now)
        self._media.service(now)
        for request in self._media.keyframe_requests:
            self._accept(request, bytes(request))
            self._inbox.append(request)
        self._media.keyframe_requests.clear()

    def _pub_send(self, data: bytes) -> None:
        # Reading EVENTS makes libzmq take in its pending commands now (a plain send only does
        # so about once a millisecond): it learns how far its queues were read, and does not
        # drop a burst that the small UPDATE_HWM can hold.
        self._pub.getsockopt(zmq.EVENTS)
        self._pub.send(data)

    def _media_fallback(self, now: float) -> bool:
        return self._media is not None and self._media.fallback(now)

    def _bundle(self, packet: Packet, data: bytes, now: float) -> None:
        assert self._media is not None
        if isinstance(packet, Bye):
            # What still waits for the budget (patches) goes first: after the Bye the
            # receiver takes nothing more of this session (nor the snapshot's refinement).
            self._bundler.drop_bulk()
            for _ in range(_MAX_DRAIN_DATAGRAMS):
                if not self._bundler.patch_bytes_waiting:
                    break
                for bundle in self._bundler.flush(now, math.inf):
                    self._media.send(bundle, now)
        if isinstance(packet, PATCH_KINDS) and (
            len(data) >= _PACED_PATCH_BYTES or self._bundler.patch_bytes_waiting
        ):
            # (A small patch behind a paced one waits too: it may refer to that one's image.)
            self._bundler.add_patch(data)
        else:
            self._bundler.add(data, frame=isinstance(packet, FRAME_KINDS))
        if isinstance(packet, Bye) or not self._paced:
            # The last datagram leaves at once, whatever it costs; so does every update of a
            # caller that does not mark its frames' ends (end_frame), which bundles nothing.
            for bundle in self._bundler.flush(now, math.inf):
                self._media.send(bundle, now)
        elif isinstance(packet, KeyFrame):
            # A keyframe leaves at once too (after a loss the receiver's picture waits for
            # it), but the patches with it only as the budget allows: paid for at any cost,
            # a full datagram of them went with every keyframe (one each 4 s), 400 ms of
            # queue on a 24 kbit/s link.
            for bundle in self._bundler.flush(now, self.budget_bps()):
                self._media.send(bundle, now)

    @property
    def spare_peers(self) -> int:
        """Receivers sent a second copy of each frame packet (they reported late frames)."""
        return len(self._spare_until)

    def _send_spare(self, data: bytes) -> None:
        now = time.monotonic()
        self._router.getsockopt(zmq.EVENTS)  # take in how far the queues were read (publish)
        for identity, until in list(self._spare_until.items()):
            if now >= until:
                del self._spare_until[identity]
                logger.info("second path closed: no late frames for %g s", SPARE_PATH_HOLD_S)
                continue
            try:
                self._router.send_multipart([identity, data], zmq.NOBLOCK, copy=False)
            except zmq.Again:
                self.spare_dropped += 1
                continue
            except zmq.ZMQError as exc:
                if exc.errno != zmq.EHOSTUNREACH:
                    raise
                del self._spare_until[identity]  # the peer is gone
                continue
            self.bytes_sent[CHANNEL_SPARE] += len(data)
            self.sizes_sent[CHANNEL_SPARE][len(data)] += 1

    def _open_spare(self, identity: bytes) -> None:
        """Send a peer that reported late frames a second copy of each frame packet."""
        if identity not in self._served_at:
            return  # it has not joined: it could not use the copies
        if self._on_udp(self._clock()) and not self._media_fallback(self._clock()):
            return  # datagrams wait behind no retransmission: a copy would only add load
        if identity not in self._spare_until:
            if len(self._spare_until) >= MAX_SNAPSHOT_PEERS:
                return
            logger.info("second path opened: a receiver reported late frames")
        self._spare_until[identity] = time.monotonic() + SPARE_PATH_HOLD_S

    def heartbeat_if_idle(self) -> bool:
        """Publish a Heartbeat if nothing was published for HEARTBEAT_INTERVAL_S; True if sent."""
        if self._clock() - self._last_publish < HEARTBEAT_INTERVAL_S:
            return False
        self.heartbeat()
        return True

    def heartbeat(self) -> None:
        """Publish a Heartbeat now (after :meth:`set_snapshot` of another session, it tells the
        receivers at once that the stream goes on in that session)."""
        self.publish(self._heartbeat())

    def _heartbeat(self) -> Heartbeat:
        session = self._snapshot.session_id if self._snapshot is not None else 0
        return Heartbeat(session, self._last_seq, self.now_us())

    def poll(self, timeout_ms: int = 0) -> list[Packet]:
        """Handle the back channel; return KeyframeRequest and ReceiverStats packets received.

        Waits up to ``timeout_ms`` for the first message. Snapshot requests and probes are
        answered here; malformed messages are counted in ``stats.malformed`` and dropped.
        """
        self._check_open()
        if not self._inbox:
            self._read_router(timeout_ms)
        self._read_router(0)
        if self._media is not None:
            self._read_media(self._clock())
            self._send_drafts(self._clock())
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
            if self._draft_waits:  # a draft waits for its receiver's path: serve that too
                self._read_router(min(10, max(1, _ms(remaining))))
                self._read_media(self._clock())
                self._send_drafts(self._clock())
            else:
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
            self._request(identity)
        elif isinstance(packet, Heartbeat):
            self._accept(packet, data)
            self._answer_probe()
        elif isinstance(packet, (KeyframeRequest, ReceiverStats)):
            self._accept(packet, data)
            self._inbox.append(packet)
            if isinstance(packet, ReceiverStats):
                self._take_stats(identity, packet.values)
        else:
            self._drop(data, f"unexpected {type(packet).__name__} on the back channel")

    def _take_stats(self, identity: bytes, values: Mapping[str, float]) -> None:
        """What a receiver's ReceiverStats say to this end: it left, took the full snapshot,
        has the snapshot (and how fast it came), or had frames come late."""
        if values.get("left"):
            self._draft_waits.pop(identity, None)
            self._forget_join(identity)
            if self._media is not None:
                self._media.forget(identity)
        if values.get(REFINED) or values.get("left"):
            self._refine.pop(identity, None)
        # A draft sent again took the time of its loss too: not the link's rate.
        snapshot_ms = 0.0 if identity in self._draft_resent else values.get(SNAPSHOT_MS)
        if identity in self._refine:
            self._refine_if_fast(identity, snapshot_ms)
        if SNAPSHOT_MS in values and self._media is not None:
            served = self._served_what.get(identity, (None, 0))[1]
            self._media.ready(identity, self._clock(), served, snapshot_ms or 0.0)
        if values.get(LATE_FRAMES, 0) > 0:
            self._open_spare(identity)

    def _answer_probe(self) -> None:
        # One published Heartbeat answers every receiver probing within PROBE_INTERVAL_MS, so
        # a flood of probes cannot multiply the published traffic.
        now = time.monotonic()
        if now - self._last_probe_answer < PROBE_INTERVAL_MS / 1000:
            self.probes_unanswered += 1
            return
        self._last_probe_answer = now
        heartbeat = self._heartbeat()
        data = bytes(heartbeat)
        self._accept_sent(heartbeat, data)
        self._pub_send(data)  # on PUB: the joining receiver proves its SUB with it

    def _request(self, identity: bytes) -> None:
        now = time.monotonic()
        if self._snapshot is None:
            if identity in self._waiting or len(self._waiting) < MAX_SNAPSHOT_PEERS:
                self._waiting[identity] = None
            else:
                self._refuse(identity, "too many requests waiting for a snapshot")
            return
        last = self._served_at.get(identity)
        if last is not None and now - last < SNAPSHOT_MIN_INTERVAL_S:
            self._refuse(identity, "asked again within the rate limit")
            return
        if identity in self._draft_waits:
            self._refuse(identity, "its draft waits for the datagram path")
            return
        version, size = self._served_what.get(identity, (None, 0))
        if identity in self._draft_by_datagram:
            # A datagram lost is not sent again: after the time it takes at the budget (with
            # room), a request again means one was.
            transfer = SNAPSHOT_TRANSFER_ROOM * size * 8 / self.max_bps
        else:
            transfer = self._transfer_s()
        if last is not None and version == self._snapshot_version and now - last < transfer:
            # On a thin link the reply is still on its way: a second copy would only queue
            # behind it (and in front of the media).
            self._refuse(identity, "the same snapshot is still on its way")
            return
        if (
            identity in self._draft_by_datagram
            and version == self._snapshot_version
            and self._media is not None
            and self._media.live_for(identity, self._clock())
        ):
            # A datagram of the draft was lost: the draft again, with the same key. A new key
            # would leave a receiver whose draft came just after it asked on a key the sender
            # no longer knows: its path down, the call on TCP.
            self._served_at[identity] = now
            self._draft_resent.add(identity)
            self._draft_waits[identity] = (self._clock() + DRAFT_PATH_WAIT_S, self._draft_bytes)
            self._send_drafts(self._clock())
            return
        if len(self._served_at) >= MAX_SNAPSHOT_PEERS:
            self._served_at = {
                peer: t for peer, t in self._served_at.items() if now - t < SNAPSHOT_MIN_INTERVAL_S
            }
            if len(self._served_at) >= MAX_SNAPSHOT_PEERS:
                self._refuse(identity, "too many peers asking")
                return
        self._serve(identity, now)

    def _transfer_s(self) -> float:
        """How long the snapshot may take to reach a receiver at this end's budget (with room
        for a link slower than the budget: three times the bare time)."""
        return SNAPSHOT_TRANSFER_ROOM * len(self._snapshot_bytes) * 8 / self.max_bps

    def _refuse(self, identity: bytes, reason: str) -> None:
        self.snapshots_refused += 1
        logger.debug("snapshot request from %s not answered: %s", identity.hex(), reason)

    def _serve(self, identity: bytes, now: float) -> None:
        reply = self._snapshot_bytes
        bare_s = self._transfer_s() / SNAPSHOT_TRANSFER_ROOM
        thin = bare_s > DRAFT_ABOVE_S and identity not in self._fast
        drafted = bool(self._draft_bytes) and self._media is not None and thin
        if drafted:
            reply = self._draft_bytes
        try:
            if self._media is not None:  # the media key first: the snapshot ends the join
                key = self._media.offer(identity, self._clock())
                data = bytes(key)
                self._router.send_multipart([identity, data], zmq.NOBLOCK)
                self._accept_sent(key, data)
                self._media.service(self._clock())  # a connecting sender's first hello
            if not drafted:
                # Never blocks: a peer that left SNAPSHOT_HWM replies unread gets no more.
                self._router.send_multipart([identity, reply], zmq.NOBLOCK, copy=False)
        except zmq.Again:
            self._refuse(identity, "earlier replies still unread")
            return
        except zmq.ZMQError as exc:
            if exc.errno != zmq.EHOSTUNREACH:
                raise
            self._refuse(identity, "peer gone")
            return
        self._served_at[identity] = now
        self._remember_served(identity, (self._snapshot_version, len(reply)))
        self._draft_by_datagram.discard(identity)
        self._draft_resent.discard(identity)
        if drafted:
            self._refine[identity] = (now, REFINE_ATTEMPTS)
            # In the datagrams, once the receiver's path is open (it opens on the key): on
            # a thin link TCP resent a segment of it, and the copy queued ahead of the first
            # frames (docs/what-we-tried.md, "Two lost in a row, and a draft sent twice").
            # (Not now: the key just made has no path yet.)
            self._draft_waits[identity] = (self._clock() + DRAFT_PATH_WAIT_S, reply)
            return
        self._count_served(reply, "")

    def _count_served(self, reply: bytes, how: str) -> None:
        self.bytes_sent[CHANNEL_SNAPSHOT] += len(reply)
        self.sizes_sent[CHANNEL_SNAPSHOT][len(reply)] += 1
        self.snapshots_served += 1
        logger.info("served the snapshot%s (%d bytes)", how, len(reply))

    def _send_drafts(self, now: float) -> None:
        """The drafts waiting for their receiver's path: in the datagrams to it once the path
        is live, all at once (as TCP would send it), or on ROUTER where it has not opened
        within DRAFT_PATH_WAIT_S (UDP blocked, or a receiver without it)."""
        if not self._draft_waits:
            return
        assert self._media is not None
        for identity, (until, draft) in list(self._draft_waits.items()):
            if self._media.live_for(identity, now):
                del self._draft_waits[identity]
                for bundle in fragments(draft, self._bundler.number(draft)):
                    self._media.send_to(identity, bundle, now)
                self._draft_by_datagram.add(identity)
                self._count_served(draft, " (its draft, in the datagrams)")
            elif now >= until:
                del self._draft_waits[identity]
                try:
                    self._router.send_multipart([identity, draft], zmq.NOBLOCK, copy=False)
                except zmq.ZMQError:
                    self._refuse(identity, "earlier replies still unread, or peer gone")
                    continue
                self._count_served(draft, " (its draft: no datagram path)")

    def _remember_served(self, identity: bytes, what: tuple[int, int]) -> None:
        """Note what ``identity`` was served, forgetting the receivers served longest ago
        beyond MAX_SNAPSHOT_PEERS: a receiver that reconnects comes back as a new identity,
        so a sender that runs for days would otherwise keep one record per connection ever
        made (and its "fast" mark: no receiver would be marked fast after the first 256)."""
        self._served_what.pop(identity, None)  # the newest last
        self._served_what[identity] = what
        while len(self._served_what) > MAX_SNAPSHOT_PEERS:
            gone = next(iter(self._served_what))
            del self._served_what[gone]
            self._forget_join(gone)

    def _forget_join(self, identity: bytes) -> None:
        """Drop the marks of how ``identity`` joined: its draft sent by datagram (and again),
        and "fast" (it left, or was served longest ago)."""
        self._fast.discard(identity)
        self._draft_by_datagram.discard(identity)
        self._draft_resent.discard(identity)

    def _refine_if_fast(self, identity: bytes, snapshot_ms: float | None) -> None:
        """The full snapshot at once on the ROUTER connection to a receiver whose draft came
        fast (a link of FAST_JOIN_BPS or more: its few kilobytes cannot hold the media up)."""
        if not snapshot_ms or len(self._draft_bytes) * 8 / (snapshot_ms / 1000) < FAST_JOIN_BPS:
            return
        del self._refine[identity]
        if len(self._fast) < MAX_SNAPSHOT_PEERS:
            self._fast.add(identity)
        self._send_full(identity, f"its draft came in {snapshot_ms:.0f} ms")

    def _send_full(self, identity: bytes, why: str) -> None:
        """The full snapshot to ``identity`` on the ROUTER connection (never blocks)."""
        logger.info("the full snapshot on the ROUTER connection: %s", why)
        try:
            self._router.send_multipart([identity, self._snapshot_bytes], zmq.NOBLOCK)
        except zmq.ZMQError:
            return
        self._count_refinement(self._snapshot_bytes)

    def _count_refinement(self, data: bytes) -> None:
        self.refinements_sent += 1
        self.bytes_sent[CHANNEL_SNAPSHOT] += len(data)

    def _send_refinements(self, now: float) -> None:
        """The full snapshot to the receivers served its draft: paced in the datagrams where
        their path is live (again every REFINE_RETRY_S until they say they took it), else at
        once on the ROUTER connection."""
        assert self._media is not None
        if any(self._bundler.holds(data) for data in self._sharper):
            # A copy is still leaving (it goes to every live receiver): a retry counts from
            # when it has gone.
            retry = now + REFINE_RETRY_S
            self._refine = {i: (max(due, retry), left) for i, (due, left) in self._refine.items()}
            return
        queued: list[bytes] = []  # sent to every live receiver at once
        for identity, (due, left) in list(self._refine.items()):
            if now < due:
                continue
            if left <= 0:
                del self._refine[identity]
                logger.info("the full snapshot was not confirmed: the receiver keeps its draft")
                continue
            live = self._media.live_for(identity, now)
            if live and max(map(len, self._sharper)) <= MAX_REASSEMBLED:
                # All in turn the first time, the full one alone again.
                again = self._sharper if left == REFINE_ATTEMPTS else self._sharper[-1:]
                for data in again:
                    if not any(data is q for q in queued):
                        self._bundler.add_bulk(data)
                        queued.append(data)
                    self._count_refinement(data)
                self._refine[identity] = (now + REFINE_RETRY_S, left - 1)
            elif not live and now - due < REFINE_RETRY_S:
                continue  # the path opens once the receiver has built its decoder
            else:
                del self._refine[identity]
                self._send_full(
                    identity,
                    f"{len(self._sharper[-1])} bytes are more than a datagram message carries"
                    if live
                    else "no datagram path to the receiver",
                )


class ReceiverEndpoint(_Endpoint):
    """The receiver's side: subscribes, fetches the snapshot, receives updates.

    ``clock`` (seconds, monotonic) times peer liveness. ``secret_key_file`` is the receiver's
    own ``.key_secret`` file (its public key must be among the sender's allowed keys) and
    ``server_key_file`` the sender's public ``.key`` file. Without them, pass ``plain=True``.

    ``bind=True`` binds both sockets on ``host`` (``"*"``: every interface; port 0: any free
    port, see :attr:`ports`) for a sender that connects; the receiver is still the CURVE client.
    """

    def __init__(
        self,
        host: str,
        pub_port: int,
        snapshot_port: int,
        context: zmq.Context[zmq.Socket[bytes]] | None = None,
        clock: Callable[[], float] = time.monotonic,
        *,
        secret_key_file: KeyFile | None = None,
        server_key_file: KeyFile | None = None,
        plain: bool = False,
        bind: bool = False,
        udp: bool = True,
    ) -> None:
        has_keys = secret_key_file is not None or server_key_file is not None
        _check_mode(plain, has_keys, "receiver", "secret_key_file, server_key_file")
        keys: KeyPair | None = None
        server_key = b""
        if not plain:
            if secret_key_file is None or server_key_file is None:
                raise TransportError(
                    "receiver: CURVE needs both secret_key_file and server_key_file"
                )
            keys = load_keypair(secret_key_file)
            server_key = load_public_key(server_key_file)
        super().__init__(context, clock)
        self._sub = _socket(self._context, zmq.SUB, UPDATE_HWM, UPDATE_HWM)
        self._sub.setsockopt(zmq.MAXMSGSIZE, MAX_UPDATE_BYTES)
        self._dealer = _socket(self._context, zmq.DEALER, BACK_CHANNEL_HWM, SNAPSHOT_HWM)
        self._sockets = [self._sub, self._dealer]
        self._curve = keys is not None
        if keys is not None:
            for sock in self._sockets:
                sock.setsockopt(zmq.CURVE_SECRETKEY, keys.secret)
                sock.setsockopt(zmq.CURVE_PUBLICKEY, keys.public)
                sock.setsockopt(zmq.CURVE_SERVERKEY, server_key)
        events = (
            zmq.EVENT_HANDSHAKE_SUCCEEDED
            | zmq.EVENT_DISCONNECTED
            | zmq.EVENT_ACCEPTED
            | zmq.EVENT_CONNECTED
            | _HANDSHAKE_FAILED
        )
        self._monitors = [sock.get_monitor_socket(events) for sock in self._sockets]
        for monitor in self._monitors:
            monitor.setsockopt(zmq.LINGER, 0)
        self._sockets += self._monitors
        self._poller = zmq.Poller()
        self._poller.register(self._sub, zmq.POLLIN)
        self._poller.register(self._dealer, zmq.POLLIN)  # the second path (frame copies)
        self._poller.register(self._monitors[0], zmq.POLLIN)
        # Subscribe first (Clone pattern), then attach the request socket.
        self._sub.setsockopt(zmq.SUBSCRIBE, b"")
        self._media: ReceiverMediaPath | None = None
        try:
            self._ports = _attach(
                [self._sub, self._dealer], host, (pub_port, snapshot_port), bind, "receiver"
            )
            self._media = _open_media(ReceiverMediaPath, host, self._ports[0], bind, udp)
        except BaseException:
            self.close()
            raise
        if self._media is not None:
            self._poller.register(self._media.fileno(), zmq.POLLIN)
        # The packets of the datagrams read, each with when its datagram was read (µs).
        self._datagram_packets: deque[tuple[bytes, int]] = deque()
        #: When the packet :meth:`recv` returned last came off the network, µs
        #: (protocol/clock.py): its datagram's or its ZeroMQ message's reading. Packets that
        #: waited in this endpoint while the caller drew a picture keep that time.
        self.arrival_us = 0
        self._recent: set[int] = set()  # digests of the last updates taken (both paths)
        self._recent_order: deque[int] = deque()
        where = "on" if bind else "from"
        self._pub_address = f"tcp://{host}:{self._ports[0]}"
        self._snapshot_address = f"tcp://{host}:{self._ports[1]}"
        self._pub_where = f"{where} {self._pub_address}"
        self._snapshot_where = f"{where} {self._snapshot_address}"
        self.snapshot: Snapshot | None = None
        self.snapshot_ms = 0.0
        #: Whether the last join's snapshot came in the datagrams (docs/protocol.md 8.7).
        self.snapshot_in_datagrams = False
        #: When this join first asked for the snapshot (None: not yet): a caller that tries
        #: in short attempts (receiver/session.py) calls fetch_snapshot() again while a draft
        #: still crosses a thin link, and timed from its last attempt the draft seemed to come
        #: at 120-200 kbit/s, and the full snapshot went after it at once, 1 s of queue.
        self._asked: float | None = None
        #: The last failed CURVE/ZMTP handshake with the sender, in words (None if none).
        self.handshake_error: str | None = None
        self._sub_dropped = False  # SUB lost its connection since the join began
        self._rejoin_reason: str | None = None
        #: Input refused to keep the live session (docs/protocol.md 3.8), logged once a second.
        self.refusals = Refusals()
        self._session_fd: int | None = None  # the SUB connection that carries the session
        self._gone: set[int] = set()  # SUB connections ended before the session's was known
        self._handshake_after_gone = False  # and a SUB connection completed its handshake since
        self._snapshot_fd: int | None = None  # the DEALER connection that brought the snapshot
        self._key_fd: int | None = None  # ... and the one that brought this join's media key
        self._keyed_at: float | None = None  # when that key came (time.monotonic())
        self._join_poller = zmq.Poller()
        self._join_poller.register(self._dealer, zmq.POLLIN)
        if self._media is not None:
            self._join_poller.register(self._media.fileno(), zmq.POLLIN)
        self._newest: tuple[int, float] = (0, clock())  # newest frame number told, and when
        self._rejoin_session: int | None = None
        self._last_heard = clock()
        self._last_seq = 0
        self._bye = False
        # The second path: the last frame packet's counter passed on, and when (and over which
        # path) each counter's first copy came; late frames not reported yet.
        self._last_counter: int | None = None
        self._first_copy: dict[int, tuple[float, bool]] = {}
        self._late = 0
        self._late_reported = -math.inf

    @property
    def ports(self) -> tuple[int, int]:
        """(pub_port, snapshot_port) connected to, or bound."""
        return self._ports

    def _release(self) -> None:
        if self._media is not None:
            self._media.close()

    @property
    def wire(self) -> WireCounts | None:
        """The media path's datagrams and their bytes on the wire (None without one)."""
        return None if self._media is None else self._media.counts

    def _media_extra(self) -> dict[str, object]:
        assert self._media is not None
        return {
            "duplicates": self.stats.duplicates,
            "patches_lost": self._media.patches_lost,
            "malformed_elements": self._media.malformed,
            "snapshot_in_datagrams": self.snapshot_in_datagrams,
        }

    @property
    def on_udp(self) -> bool:
        """Whether the media come as datagrams now (else on SUB)."""
        return self._media is not None and self._media.live(self._clock())

    def _seen(self, data: bytes) -> bool:
        """Whether these very bytes were taken lately (else remember them)."""
        digest = hash(data)
        if digest in self._recent:
            return True
        self._recent.add(digest)
        self._recent_order.append(digest)
        if len(self._recent_order) > _RECENT_UPDATES:
            self._recent.discard(self._recent_order.popleft())
        return False

    def _read_datagrams(self) -> None:
        if self._media is None:
            return
        now = self._clock()
        now_ms = round(now * 1000)
        read_us = now_us()
        self._datagram_packets.extend((data, read_us) for data in self._media.read(now, now_ms))
        self._media.service(now, now_ms)

    @property
    def peer_alive(self) -> bool:
        """False after PEER_TIMEOUT_S without a well-formed packet, or after a Bye."""
        return not self._bye and self._clock() - self._last_heard < PEER_TIMEOUT_S

    @property
    def session_id(self) -> int | None:
        """The session of the current snapshot (None before the first one)."""
        return None if self.snapshot is None else self.snapshot.session_id

    def fetch_snapshot(self, timeout_ms: int = 5000) -> Snapshot:
        """Run the joining handshake and return the sender's Snapshot.

        Call it again to rejoin (after :class:`RejoinNeeded`, or when the peer is lost): the
        updates still queued from the old stream are discarded first. Raises TransportError if
        the sender does not answer within ``timeout_ms``.
        """
        self._check_open()
        if self.snapshot is not None:
            self._forget()
        self._datagram_packets.clear()
        self._last_counter = None
        self._first_copy.clear()
        self._read_events()
        self._sub_dropped = False
        self._gone.clear()
        self._handshake_after_gone = False
        deadline = time.monotonic() + timeout_ms / 1000
        # 1. Prove the subscription is live: probe until SUB has something to read.
        while not self._sub.poll(0, zmq.POLLIN):
            remaining = _ms(deadline - time.monotonic())
            if remaining <= 0:
                self._read_events()
                self._asked = None  # the sender is not there: the next join starts afresh
                raise TransportError(
                    f"no published packet {self._pub_where} within {timeout_ms} ms "
                    f"(is the sender running?){self._handshake_hint()}"
                )
            self._send(self._probe())
            self._sub.poll(min(PROBE_INTERVAL_MS, remaining), zmq.POLLIN)
        # 2. Ask for the snapshot (again every SNAPSHOT_RETRY_MS, in case a request was lost
        # or refused by the rate limit); updates keep queueing on SUB meanwhile.
        next_request = 0.0
        if self._asked is None:
            self._asked = time.monotonic()
        while True:
            now = time.monotonic()
            remaining = _ms(deadline - now)
            if remaining <= 0:
                self._read_events()
                raise TransportError(
                    f"no snapshot {self._snapshot_where} within {timeout_ms} ms"
                    f"{self._handshake_hint()}"
                )
            if now >= next_request:
                self._send(SnapshotRequest())
                next_request = now + SNAPSHOT_RETRY_MS / 1000
            wait = min(remaining, _ms(next_request - now) + 1)
            if self._media is not None and self._media.keyed:
                # Open the media path while the snapshot crosses: the first frame after the
                # join then goes as a datagram, not on PUB behind the snapshot's TCP queue;
                # a draft comes that way itself (docs/protocol.md 8.7).
                self._read_datagrams()
                came = self._datagram_snapshot()
                if came is not None:
                    return self._joined(*came, self._key_fd, in_datagrams=True)
                wait = min(wait, _ms(HELLO_INTERVAL_S))
                # The datagrams wake the join too: a draft may come that way.
                ready = dict(self._join_poller.poll(wait))
                if self._dealer not in ready:
                    continue  # a datagram (read above on the next turn), or the beat
            elif not self._dealer.poll(wait, zmq.POLLIN):
                continue
            message = self._dealer.recv(copy=False)
            data = message.bytes
            try:
                packet = decode(data)
            except PacketError as exc:
                self._drop(data, str(exc))
                continue
            if isinstance(packet, FRAME_KINDS):
                continue  # a second-path copy of the stream being left
            if isinstance(packet, MediaKey):
                self._accept(packet, data)
                self._key_fd = _source(message)
                self._keyed_at = time.monotonic()
                if self._media is not None and packet.udp:
                    self._media.take_key(packet, self._clock())
                    self._read_datagrams()  # the first hello
                continue
            if not isinstance(packet, Snapshot):
                self._drop(data, f"unexpected {type(packet).__name__} on the snapshot channel")
                continue
            return self._joined(packet, data, _source(message))

    def _datagram_snapshot(self) -> tuple[Snapshot, bytes] | None:
        """A Snapshot among the packets of the datagrams read (sealed with this join's key:
        the sender's), taken out of them."""
        for i, (data, _) in enumerate(self._datagram_packets):
            if data[:1] != _SNAPSHOT_BYTE:
                continue
            del self._datagram_packets[i]
            try:
                packet = decode(data)
            except PacketError as exc:
                self._drop(data, str(exc))
                return None
            return (packet, data) if isinstance(packet, Snapshot) else None
        return None

    def _joined(
        self, packet: Snapshot, data: bytes, fd: int | None, in_datagrams: bool = False
    ) -> Snapshot:
        """The join's snapshot has come (on the connection ``fd``, or in a datagram after
        the key that came on it)."""
        self._take_snapshot(packet, data)
        self._snapshot_fd = fd
        self.snapshot_in_datagrams = in_datagrams
        self._newest = (packet.seq, self._clock())
        #: How long the snapshot took to come, ms (from the first request; a draft in the
        #: datagrams from its key): the sender learns from it whether the link is fast
        #: (docs/protocol.md 8.7).
        since = self._keyed_at if in_datagrams else self._asked
        self.snapshot_ms = (time.monotonic() - (since or time.monotonic())) * 1000
        self._asked = None
        if self._media is not None:
            self._media.joined(self._clock())
        how = " (in the datagrams)" if in_datagrams else ""
        logger.info("snapshot%s: session %d from seq %d", how, packet.session_id, packet.seq)
        return packet

    def recv(self, timeout_ms: int = 0) -> Packet | None:
        """The next update at or after the snapshot's seq, or None after ``timeout_ms``.

        Returns KeyFrame, DeltaFrame, RemPatch, Refresh, AudioFrame, Heartbeat, Bye or a new
        Snapshot.
        Malformed
        messages are counted in ``stats.malformed`` and dropped; bad input never raises.
        Raises :class:`RejoinNeeded` (until :meth:`fetch_snapshot` is called again) once the
        session's SUB connection has dropped and come back, or it names another session.
        """
        self._check_open()
        if self.snapshot is None:
            raise TransportError("call fetch_snapshot() before recv()")
        deadline = time.monotonic() + timeout_ms / 1000
        while True:
            # Events first: the handshake of a new connection is reported before any message
            # that connection brings, so no update of a new session is taken for the old one.
            self._read_events()
            if self._rejoin_reason is not None:
                raise RejoinNeeded(
                    f"{self._rejoin_reason}; call fetch_snapshot() to rejoin", self._rejoin_session
                )
            self._report_late()
            self._read_datagrams()
            if self._datagram_packets:
                data, read_us = self._datagram_packets.popleft()
                packet = self._take(data)
                if packet is not None:
                    self.arrival_us = read_us
                    return packet
                continue
            try:
                packet = self._update(self._sub.recv_multipart(zmq.NOBLOCK, copy=False))
                self.arrival_us = now_us()
            except zmq.Again:
                try:
                    packet = self._update(
                        self._dealer.recv_multipart(zmq.NOBLOCK, copy=False), spare=True
                    )
                    self.arrival_us = now_us()
                except zmq.Again:
                    remaining = _ms(deadline - time.monotonic())
                    if remaining <= 0:
                        return None
                    # Wake for the media path's reports and hellos too.
                    self._poller.poll(min(remaining, _ms(HURRIED_REPORT_INTERVAL_S / 2)))
                    continue
            if packet is not None:
                return packet

    def note_late_frame(self) -> None:
        """Tell the sender (at most every LATE_REPORT_S) that a frame came late: it then sends
        frame packets over the second path too. The caller judges lateness (it knows the
        frames' capture times: receiver/lateness.py)."""
        self.stats.late_frames += 1
        if self.on_udp:
            return  # a datagram waits behind no retransmission: a second copy cannot help
        self._late += 1
        self._report_late()

    def _report_late(self) -> None:
        now = time.monotonic()
        if self._late and now - self._late_reported >= LATE_REPORT_S:
            self.send_stats({LATE_FRAMES: float(self._late)})
            self._late = 0
            self._late_reported = now

    def request_keyframe(self, seq: int) -> None:
        """Ask the sender for a keyframe; ``seq`` is the last frame decoded. On DEALER, and
        in a datagram too where the media path is live (docs/protocol.md 8.6)."""
        request = KeyframeRequest(seq)
        self._send(request)
        if self._media is not None:
            self._media.send_request(request, self._clock())

    def send_stats(self, values: Mapping[str, float]) -> None:
        """Send named statistics (finite floats) to the sender."""
        self._send(ReceiverStats(values))

    def _probe(self) -> Heartbeat:
        return Heartbeat(self.session_id or 0, self._last_seq, self.now_us())

    def _send(self, packet: Packet) -> None:
        self._check_open()
        data = bytes(packet)
        try:
            self._dealer.send(data, zmq.NOBLOCK)
        except zmq.Again:
            logger.debug("back channel full, dropped %s", type(packet).__name__)
            return
        self.bytes_sent[CHANNEL_CONTROL] += len(data)
        self.sizes_sent[CHANNEL_CONTROL][len(data)] += 1

    def _forget(self) -> None:
        """Drop the old stream before a rejoin: its queued updates must not pass as new ones."""
        self.snapshot = None
        self._rejoin_reason = None
        self._rejoin_session = None
        self._bye = False
        self._session_fd = None
        for _ in range(4 * UPDATE_HWM):
            try:
                self._sub.recv_multipart(zmq.NOBLOCK)
            except zmq.Again:
                break

    def _read_events(self) -> None:
        for monitor in self._monitors:
            while True:
                try:
                    event = recv_monitor_message(monitor, zmq.NOBLOCK)
                except zmq.Again:
                    break
                self._on_event(monitor is self._monitors[0], event["event"], event["value"])

    def _on_event(self, on_sub: bool, kind: int, value: int) -> None:
        if kind & _HANDSHAKE_FAILED:
            self.handshake_error = _describe_failure(kind, value, self._curve)
            logger.info("handshake with the sender failed: %s", self.handshake_error)
        elif on_sub and kind == zmq.EVENT_DISCONNECTED:
            # Only the session's own connection counts (a bound SUB takes anyone's): a
            # stranger that connects and leaves changes nothing. What that connection brought
            # before it ended (its Bye) is still the session's.
            if value == self._session_fd:
                self._sub_dropped = True
            elif self._session_fd is None:
                self._gone.add(value)
        elif on_sub and kind in (zmq.EVENT_ACCEPTED, zmq.EVENT_CONNECTED):
            self._gone.discard(value)  # a new connection with an old one's number
        elif on_sub and kind == zmq.EVENT_HANDSHAKE_SUCCEEDED:
            self.handshake_error = None
            self._handshake_after_gone = self._handshake_after_gone or bool(self._gone)
            if self._sub_dropped and self.snapshot is not None and self._rejoin_reason is None:
                self._rejoin_reason = "the sender's connection dropped and came back"
                logger.info("%s", self._rejoin_reason)

    def _handshake_hint(self) -> str:
        return "" if self.handshake_error is None else f"; {self.handshake_error}"

    def _take_snapshot(self, snapshot: Snapshot, data: bytes) -> None:
        self.snapshot = snapshot
        self._accept(snapshot, data)
        self._last_heard = self._clock()

    def _first(self, packet: KeyFrame | DeltaFrame, spare: bool) -> bool:
        """Whether this is the first copy of its frame packet.

        A packet whose counter (5.6) was taken less than COPY_WINDOW_S ago, and is not the
        next one (a fast sender's counter may come round within the window), is a second copy
        and is dropped; if it came LATE_FRAME_MS or more after the first, the path it came by
        waited for a retransmission, which counts as a late frame. A second-path copy that is
        not the next packet is dropped too (its queue lost one, or it is behind): the PUB path
        brings the packets in between. A KeyFrame needs nothing before it.
        """
        now = time.monotonic()
        last = self._last_counter
        next_one = last is None or packet.counter == (last + 1) % COUNTER_MOD
        first = self._first_copy.get(packet.counter)
        if first is not None and now - first[0] < COPY_WINDOW_S and not next_one:
            self.stats.copies += 1
            if now - first[0] >= LATE_FRAME_MS / 1000:
                self.stats.late_copies += 1
                self.stats.saved += first[1]
                self._late += 1
            return False
        if spare and not next_one and not isinstance(packet, KeyFrame):
            self.stats.copies += 1
            return False
        self._last_counter = packet.counter
        self._first_copy[packet.counter] = (now, spare)
        return True

    def _update(self, frames: list[zmq.Frame], spare: bool = False) -> Packet | None:
        """An update from SUB, or (``spare``) from DEALER after the join: a frame packet's
        second copy, or a snapshot reply that came too late to matter."""
        fd = _source(frames[0])
        if spare and fd != self._snapshot_fd:
            # Not even decoded: a stranger on a bound DEALER may send 16 MiB messages.
            self._ignore("ignored a message from another connection to DEALER")
            return None
        data = b"".join(f.bytes for f in frames)
        if len(frames) != 1:
            self._drop(data, f"{len(frames)}-part message")
            return None
        return self._take(data, spare, fd)

    def _take(self, data: bytes, spare: bool = False, fd: int | None = None) -> Packet | None:
        """An update's bytes, from SUB or the second path (``spare``) on connection ``fd``,
        or (``fd`` None) from a datagram, sealed with this join's key."""
        try:
            packet = decode(data)
        except PacketError as exc:
            self._drop(data, str(exc))
            return None
        if spare:
            if not isinstance(packet, FRAME_KINDS):
                if isinstance(packet, Snapshot) and packet.session_id == self.session_id:
                    self._take_snapshot(packet, data)
                    return packet  # the full one after a draft (docs/protocol.md 8.7)
                if isinstance(packet, Snapshot):
                    logger.debug("dropped a snapshot reply that came after the join")
                else:
                    self._drop(data, f"unexpected {type(packet).__name__} on the snapshot channel")
                return None
        elif not isinstance(packet, UPDATE_KINDS):
            self._drop(data, f"unexpected {type(packet).__name__} on the update channel")
            return None
        if not self._of_session(packet, fd, spare):
            return None
        if (
            not spare
            and isinstance(packet, MEDIA_KINDS)
            and self._media is not None
            and self._seen(data)
        ):
            # The same update by both paths: the sender publishes on PUB too while a path is
            # opening or down.
            self.stats.duplicates += 1
            return None
        if isinstance(packet, Snapshot):
            if packet.session_id != self.session_id:
                # A full snapshot still in flight for a session left (docs/protocol.md 8.7).
                logger.debug("dropped a snapshot of session %d", packet.session_id)
                return None
            self._take_snapshot(packet, data)
            return packet
        assert self.snapshot is not None
        self._last_heard = self._clock()
        self._bye = isinstance(packet, Bye)
        if isinstance(packet, (KeyFrame, Heartbeat)) and packet.seq > self._newest[0]:
            self._newest = (packet.seq, self._clock())
        if isinstance(packet, SEQ_KINDS) and packet.seq < self.snapshot.seq:
            self.stats.dropped_old += 1
            return None
        if isinstance(packet, FRAME_KINDS) and not self._first(packet, spare):
            self.bytes_received[CHANNEL_SPARE] += len(data)
            self.sizes_received[CHANNEL_SPARE][len(data)] += 1
            return None
        if isinstance(packet, KeyFrame):
            self._last_seq = packet.seq
        self.stats.received += 1
        self.bytes_received[packet.CHANNEL] += len(data)
        self.sizes_received[packet.CHANNEL][len(data)] += 1
        return packet

    def _of_session(self, packet: Packet, fd: int | None, spare: bool) -> bool:
        """Whether an update belongs to the live session (docs/protocol.md 3.8).

        On SUB the session's packets come by one connection, the first that brought one naming
        the session; packets by another connection are ignored (counted), so a second sender
        or a stranger can neither switch nor end the session. A packet naming another session
        asks for a rejoin only when the session's own connection (or its datagrams) brings it:
        the sender itself began a new session. A Bye whose seq lies beyond any frame the
        sender can have sent by now is refused.
        """
        assert self.snapshot is not None
        mine = self.snapshot.session_id
        session = getattr(packet, "session_id", None)
        kind = type(packet).__name__
        on_sub = fd is not None and not spare
        if on_sub and self._session_fd is not None and fd != self._session_fd:
            self._ignore(f"ignored a {kind} from a second connection to SUB (another sender?)")
            return False
        if session is not None and session != mine:
            if isinstance(packet, Heartbeat) and session == 0:
                return False  # a probe's answer from before the sender had a session
            if not spare and (fd is None or fd == self._session_fd):
                self._rejoin_reason = f"the sender's session changed ({mine} -> {session})"
                self._rejoin_session = session
                logger.info("%s", self._rejoin_reason)
            else:
                self._ignore(f"ignored a {kind} of session {session}: session {mine} is live")
            return False
        if on_sub and self._session_fd is None:
            if session is None and isinstance(packet, Bye):
                self._ignore("ignored a Bye before the session's connection was known")
                return False
            if session is not None:
                self._session_fd = fd
                self._read_events()  # (the connection's number may have been taken again)
                if fd in self._gone:  # it brought the session, then ended
                    self._sub_dropped = True
                    if self._handshake_after_gone:  # and another came: 3.2's reconnection
                        self._rejoin_reason = "the sender's connection dropped and came back"
                        logger.info("%s", self._rejoin_reason)
                        return False
        if isinstance(packet, Bye) and not self._bye_in_reach(packet.seq):
            self.stats.malformed += 1
            self.refusals.refuse(
                f"refused a Bye at frame {packet.seq}: the sender is near frame "
                f"{self._newest[0]}"
            )  # fmt: skip
            return False
        return True

    def _bye_in_reach(self, seq: int) -> bool:
        """Whether a sender can have reached frame ``seq`` by now: the newest frame number it
        told (a KeyFrame, a Heartbeat or the snapshot), one frame for each frame interval
        since, and MAX_SEQ_STEP (a delta's longest step) to spare."""
        assert self.snapshot is not None
        newest, heard_at = self._newest
        since = max(0.0, self._clock() - heard_at)
        return seq <= newest + MAX_SEQ_STEP + math.ceil(since * self.snapshot.fps)

    def _ignore(self, why: str) -> None:
        self.stats.ignored_sessions += 1
        self.refusals.refuse(why)


def _source(frame: zmq.Frame) -> int:
    """The connection (its file descriptor) a message came by."""
    return int(frame.get(zmq.SRCFD))


def _describe_failure(kind: int, value: int, curve: bool) -> str:
    if kind == zmq.EVENT_HANDSHAKE_FAILED_AUTH:
        return (
            f"the sender refused this receiver's key (ZAP status {value}; is its public key "
            "among the sender's allowed keys?)"
        )
    if kind == zmq.EVENT_HANDSHAKE_FAILED_PROTOCOL:
        return (
            "CURVE/ZMTP handshake failed (protocol error "
            f"{value:#x}: wrong server key, or one end is plain and the other encrypted?)"
        )
    if curve and value in (errno.EPIPE, errno.ECONNRESET):
        # A CURVE server that cannot open the client's HELLO (made for another server key)
        # closes the connection without a word.
        return (
            "handshake failed: the sender's key does not match the one this end holds for it "
            "(--peer), or it is another program"
        )
    return f"handshake failed (errno {value}: {os.strerror(value)})"
