"""The media path for thin links: the call's updates as sealed UDP datagrams (version 3).

ZeroMQ keeps what needs reliability (joining, the snapshot, the back channel) and hands over the
keys: just before the snapshot the sender sends the receiver a :class:`MediaKey` on the
CURVE-secured ROUTER/DEALER connection. From then on frame packets, REM patches, sound,
heartbeats and the Bye travel bundled in datagrams (protocol/bundle.py) sealed with that key
(protocol/datagram.py), and the receiver's reception reports come back the same way.

Addresses: the end that binds its ZeroMQ sockets also binds a UDP socket on its first port's
number (UDP and TCP ports are separate spaces); the end that connects sends to that address.
Each end answers wherever the other's authentic datagrams come from (RTP's "symmetric" latching,
so a NAT in between does no harm). The connecting end opens the path: it sends an empty
datagram every HELLO_INTERVAL_S until the other answers.

Fallback: a path is live while an authentic datagram came within PATH_TIMEOUT_S. A receiver
that has not heard the sender's datagrams for that long (UDP blocked, or a firewall opened
for TCP only) goes back to its SUB socket; a sender that has not heard a receiver's datagrams
for that long publishes on PUB again (docs/protocol.md, 7.5). Each switch is logged in one line.

:class:`Bundler` decides what goes in each datagram and when: everything due goes into one,
one datagram per FRAMES_PER_DATAGRAM frames (fewer when the budget is thin), and REM patches,
sliced where need be, take what the budget leaves.
"""

from __future__ import annotations

import contextlib
import ipaddress
import logging
import math
import os
import socket
import struct
import sys
import time
from collections import deque
from dataclasses import dataclass, field

from facewire.protocol.bundle import (
    FRAGMENT,
    FRAGMENT_HEADER,
    HURRY,
    MAX_DATAGRAM,
    MAX_REASSEMBLED,
    REPORT,
    BundleError,
    Fragment,
    Reassembly,
    Report,
    element_size,
    pack,
    unpack,
)
from facewire.protocol.congestion import RateController
from facewire.protocol.constants import PROTOCOL_VERSION
from facewire.protocol.datagram import (
    IP_UDP_BYTES,
    OVERHEAD,
    RECEIVER_TO_SENDER,
    SENDER_TO_RECEIVER,
    DatagramError,
    Opener,
    Sealer,
    key_id_of,
    new_secret,
)
from facewire.protocol.packets import (
    KeyframeRequest,
    Kind,
    MediaKey,
    PacketError,
    decode,
    header_byte,
)

logger = logging.getLogger(__name__)

#: A path with no authentic datagram for this long is down; the media go by ZeroMQ instead.
#: Shorter than PEER_TIMEOUT_S, so the media are back on PUB before a receiver would give its
#: peer up (the sender heartbeats at least every second, the receiver reports every 0.5 s).
PATH_TIMEOUT_S = 1.5
#: A path that never opened is timed from when its receiver has the snapshot (it says so:
#: "ready"), not from its key: the key goes just before the snapshot, whose draft takes 1.2 s
#: to cross a 16 kbit/s link, and the sender's first datagrams wait behind it. Without a word
#: from the receiver, from this long after its key.
READY_WAIT_S = 8.0
#: The connecting end's empty datagrams while the path is not open yet, then while it is down.
HELLO_INTERVAL_S = 0.1
REPROBE_INTERVAL_S = 2.0
#: The receiver's reception reports (what the rate control reads), one every so often; at the
#: faster beat for HURRY_HOLD_S after the path opens and after a datagram with a Hurry element
#: (the sender's rate control has something to follow: RateController.wants_reports), which the
#: sender puts in a datagram at most every HURRY_EVERY_S while it wants them.
REPORT_INTERVAL_S = 0.5
HURRIED_REPORT_INTERVAL_S = 0.25
HURRY_HOLD_S = 1.0
HURRY_EVERY_S = 0.25
_HURRY_ELEMENT = bytes([HURRY])
#: Bytes on the wire per datagram besides its bundle: IPv4, UDP and the datagram's own 12.
DATAGRAM_COST = IP_UDP_BYTES + OVERHEAD
#: The on-the-wire budget of one direction when none is given (the media of a call with sound
#: fit in it with room for the datagrams' headers), bits per second.
DEFAULT_BUDGET_BPS = 32_000.0
#: The datagrams' headers take at most this share of the budget: one datagram per frame when
#: the budget is wide, one per two, three or four frames as it narrows.
HEADER_SHARE = 0.25
#: ... and at most this share where the link loses datagrams: a lost datagram's frames come
#: again in the next one, so the frames a datagram waits for are also how late they come then
#: (one datagram a frame at the default budget: 33 ms at 30 fps instead of 67).
LOSSY_HEADER_SHARE = 0.4
MAX_FRAMES_PER_DATAGRAM = 4
#: The token bucket of the sender's pacing holds this many seconds of the budget at most, and
#: no more than one datagram interval's: a datagram never takes longer than that to cross a
#: link at the budget's rate, so a patch slice cannot hold the next frame's datagram up (a
#: full 1200-byte datagram takes 400 ms at 24 kbit/s).
BUCKET_S = 0.25
#: Most datagrams read per call (bounds the time spent under a flood).
_MAX_READ = 256
_RECV_BYTES = 2048  # more than any datagram we send: a longer one is not ours
#: Linux's SO_TIMESTAMPNS (asm-generic/socket.h; Python names only SO_TIMESTAMP): the kernel
#: stamps each datagram's arrival, so the reports' arrival times do not wait for the
#: receiver's loop (a frame being drawn would look like a queue on the link to the rate
#: control). Its control message holds a struct timespec on CLOCK_REALTIME.
_SO_TIMESTAMPNS = 35
_TIMESPEC = struct.Struct("@ll")
_ANCILLARY_BYTES = socket.CMSG_SPACE(_TIMESPEC.size)
MAX_STAMP_AGE_S = 1.0
RECEIVE_BUFFER_BYTES = 1 << 20
KEYFRAME_REQUEST_BYTE = header_byte(Kind.KEYFRAME_REQUEST)


def frames_per_datagram(
    budget_bps: float, fps: float, lossy: bool = False, header_bytes: int = DATAGRAM_COST
) -> int:
    """Frames whose updates share one datagram: the fewest that keep the datagrams' headers
    (``header_bytes`` each: none to a receiver on this machine) within HEADER_SHARE of the
    budget (LOSSY_HEADER_SHARE on a ``lossy`` link), at most MAX_FRAMES_PER_DATAGRAM."""
    share = LOSSY_HEADER_SHARE if lossy else HEADER_SHARE
    for k in range(1, MAX_FRAMES_PER_DATAGRAM):
        if header_bytes * 8 * fps / k <= share * budget_bps:
            return k
    return MAX_FRAMES_PER_DATAGRAM


def _is_loopback(address: tuple[str, int] | None) -> bool:
    """Whether a peer's UDP address is a loopback one (127.0.0.0/8, ::1)."""
    if address is None:
        return False
    try:
        return ipaddress.ip_address(address[0]).is_loopback
    except ValueError:
        return False


def _address(host: str, port: int) -> tuple[str, int]:
    """An IPv4 address for ``host`` (resolved once: sendto would resolve it every time)."""
    info = socket.getaddrinfo(host, port, socket.AF_INET, socket.SOCK_DGRAM)
    address = info[0][4]
    return str(address[0]), int(address[1])


def _udp_socket(host: str, port: int, bind: bool) -> tuple[socket.socket, tuple[str, int] | None]:
    """A non-blocking UDP socket: bound on ``host:port`` (``bind``), else on any free port with
    ``host:port`` as the peer to open the path to; the kernel stamps arrivals where it can."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setblocking(False)
        if sys.platform.startswith("linux"):
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
        with contextlib.suppress(OSError):
            # Room for a Bye's drain (up to _MAX_DRAIN_DATAGRAMS full datagrams at once) while
            # the receiver draws a frame (the kernel caps it at net.core.rmem_max).
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
        if bind:
            sock.bind(("0.0.0.0" if host in ("*", "") else host, port))
            return sock, None
        sock.bind(("0.0.0.0", 0))
        return sock, _address(host, port)
    except BaseException:
        sock.close()
        raise


@dataclass
class WireCounts:
    """Datagrams and their bytes on the wire (IPv4 and UDP headers counted)."""

    datagrams_sent: int = 0
    wire_bytes_sent: int = 0
    datagrams_received: int = 0
    wire_bytes_received: int = 0
    #: Dropped datagrams, by why: not ours or truncated, forged/altered, replayed.
    dropped: dict[str, int] = field(default_factory=dict)

    def drop(self, reason: str) -> None:
        self.dropped[reason] = self.dropped.get(reason, 0) + 1


def _why(exc: DatagramError) -> str:
    text = str(exc)
    if "replayed" in text:
        return "replayed"
    if "authentication" in text:
        return "forged"
    return "malformed"


class _Path:
    """What both ends share: the socket, the counts, liveness and the hellos."""

    def __init__(self, host: str, port: int, bind: bool, side: str) -> None:
        self.sock, self.dest = _udp_socket(host, port, bind)
        self.side = side
        self.counts = WireCounts()
        self.closed = False

    def fileno(self) -> int:
        return self.sock.fileno()

    def _sendto(self, datagram: bytes, address: tuple[str, int]) -> bool:
        try:
            self.sock.sendto(datagram, address)
        except (BlockingIOError, InterruptedError):
            self.counts.drop("send_queue_full")
            return False
        except OSError as exc:  # no route, unreachable port reported by ICMP
            logger.debug("%s: datagram to %s not sent: %s", self.side, address, exc)
            return False
        self.counts.datagrams_sent += 1
        self.counts.wire_bytes_sent += len(datagram) + IP_UDP_BYTES
        return True

    def _recv(self) -> tuple[bytes, tuple[str, int], float] | None:
        """(datagram, where from, seconds since it arrived: 0 where the kernel did not say)."""
        try:
            data, ancillary, _, address = self.sock.recvmsg(_RECV_BYTES, _ANCILLARY_BYTES)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError as exc:  # an ICMP error queued on the socket
            logger.debug("%s: %s", self.side, exc)
            return b"", ("", 0), 0.0
        self.counts.datagrams_received += 1
        self.counts.wire_bytes_received += len(data) + IP_UDP_BYTES
        age = 0.0
        for level, kind, value in ancillary:
            if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(value) >= 16:
                seconds, nanoseconds = _TIMESPEC.unpack_from(value)
                age = time.time() - (seconds + nanoseconds / 1e9)
        # A wall clock that stepped (NTP) makes the stamp say nothing: the loop's time then.
        return data, address, age if 0.0 < age < MAX_STAMP_AGE_S else 0.0

    def _open(self, opener: Opener, data: bytes) -> tuple[int, list[bytes]] | None:
        """(packet index, elements) of an authentic datagram, else None (counted by why)."""
        try:
            index, bundle = opener.open(data)
            return index, list(unpack(bundle))
        except DatagramError as exc:
            self.counts.drop(_why(exc))
        except BundleError:
            self.counts.drop("malformed")
        return None

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.sock.close()


# --- the sender's end ---------------------------------------------------------------------------


@dataclass
class _Receiver:
    """One receiver the sender gave a key."""

    key_id: int
    sealer: Sealer
    opener: Opener
    offered_at: float
    address: tuple[str, int] | None = None
    last_heard: float = -math.inf
    controller: RateController = field(default_factory=RateController)
    live_told: bool = False
    fallback_told: bool = False
    last_hello: float = -math.inf
    ready_at: float | None = None  # when it said it has the snapshot

    def live(self, now: float) -> bool:
        return self.address is not None and now - self.last_heard < PATH_TIMEOUT_S

    def down(self, now: float) -> bool:
        """No live path for PATH_TIMEOUT_S since its last datagram and since the receiver said
        it has the snapshot (READY_WAIT_S after its key while it has not said so).

        Until it says so, a receiver's silence means nothing: its first hello comes with its
        key, and then it builds its decoder without reading its socket (1.7 s on a cold start,
        the first `facewire demo` after a boot, where the sender said UDP was blocked)."""
        if self.live(now):
            return False
        ready = self.ready_at if self.ready_at is not None else self.offered_at + READY_WAIT_S
        return now - max(self.last_heard, ready) >= PATH_TIMEOUT_S


class SenderMediaPath(_Path):
    """The sender's UDP socket and the receivers it has keyed (by ROUTER identity)."""

    def __init__(self, host: str, port: int, bind: bool) -> None:
        super().__init__(host, port, bind, "sender")
        self._by_identity: dict[bytes, _Receiver] = {}
        self._by_key: dict[int, _Receiver] = {}
        self._next_key = int.from_bytes(os.urandom(1), "big")
        #: Keyframe requests that came in the receivers' datagrams, for the caller to take.
        self.keyframe_requests: list[KeyframeRequest] = []

    def offer(self, identity: bytes, now: float) -> MediaKey:
        """A new key for the receiver ``identity`` (replacing any it had)."""
        self.forget(identity)
        if len(self._by_key) >= 256:
            oldest = min(self._by_identity, key=lambda i: self._by_identity[i].offered_at)
            self.forget(oldest)
        while self._next_key in self._by_key:
            self._next_key = (self._next_key + 1) % 256
        key_id, self._next_key = self._next_key, (self._next_key + 1) % 256
        secret = new_secret()
        peer = _Receiver(
            key_id,
            Sealer(secret, SENDER_TO_RECEIVER, key_id),
            Opener(secret, RECEIVER_TO_SENDER, key_id),
            now,
        )
        self._by_identity[identity] = self._by_key[key_id] = peer
        return MediaKey(key_id, secret, 1)

    def ready(self, identity: bytes, now: float, served: int = 0, snapshot_ms: float = 0) -> None:
        """The receiver ``identity`` has the snapshot, whose ``served`` bytes took
        ``snapshot_ms`` to come: its path can open from now on, and its rate control starts
        from that transfer's rate."""
        peer = self._by_identity.get(identity)
        if peer is not None and peer.ready_at is None:
            peer.ready_at = now
            peer.controller.on_join(served * 8, snapshot_ms / 1000)

    def forget(self, identity: bytes) -> None:
        peer = self._by_identity.pop(identity, None)
        if peer is not None:
            del self._by_key[peer.key_id]

    def read(self, now: float) -> None:
        """Take in the receivers' datagrams: open paths, reception reports."""
        for _ in range(_MAX_READ):
            got = self._recv()
            if got is None:
                return
            data, address, _ = got
            key_id = key_id_of(data)
            peer = None if key_id is None else self._by_key.get(key_id)
            if peer is None:
                self.counts.drop("malformed")
                continue
            opened = self._open(peer.opener, data)
            if opened is None:
                continue
            # A receiver's datagram carries reports, and its keyframe requests (a copy of
            # those it sends on DEALER: over a lossy link TCP holds a lost request, and every
            # one behind it, for a retransmission, and the picture stays frozen meanwhile).
            try:
                reports = [Report.parse(e) for e in opened[1] if e[0] == REPORT]
                requests = [decode(e) for e in opened[1] if e[0] == KEYFRAME_REQUEST_BYTE]
            except (BundleError, PacketError):
                reports, requests = [], []
            if len(reports) + len(requests) != len(opened[1]):
                self.counts.drop("malformed")
                continue
            fresh = not peer.live(now)
            peer.address, peer.last_heard = address, now
            if fresh:
                self._opened(peer, now)
            for report in reports:
                peer.controller.on_report(
                    now, report.highest, report.arrival_ms, report.received, report.received_bytes
                )
            self.keyframe_requests += [r for r in requests if isinstance(r, KeyframeRequest)]

    def _opened(self, peer: _Receiver, now: float) -> None:
        if not peer.live_told or peer.fallback_told:
            logger.info(
                "media: datagrams (UDP) with the receiver at %s:%d", *(peer.address or ("?", 0))
            )
        peer.live_told, peer.fallback_told = True, False
        self._seal_to(peer, b"", now)  # the receiver learns the path works both ways

    def service(self, now: float) -> None:
        """Hellos from a connecting sender; one line when a receiver's path goes down."""
        for peer in self._by_key.values():
            if peer.live(now):
                continue
            if self.dest is not None and now - peer.last_hello >= HELLO_INTERVAL_S:
                peer.last_hello = now
                self._seal_to(peer, b"", now, self.dest)
            if peer.down(now):
                if not peer.fallback_told:
                    peer.fallback_told = True
                    logger.warning(
                        "media: no datagram from a receiver for %g s (UDP blocked?): "
                        "its media go by ZeroMQ over TCP",
                        PATH_TIMEOUT_S,
                    )

    def live_for(self, identity: bytes, now: float) -> bool:
        """Whether the receiver ``identity`` takes datagrams now."""
        peer = self._by_identity.get(identity)
        return peer is not None and peer.live(now)

    def live(self, now: float) -> list[_Receiver]:
        return [p for p in self._by_key.values() if p.live(now)]

    def fallback(self, now: float) -> bool:
        """Whether a keyed receiver has no live path (its media must go by PUB)."""
        return any(p.down(now) for p in self._by_key.values())

    def budget_bps(self, now: float, most: float, congested_only: bool = False) -> float:
        """The sending budget: ``most``, or less where a receiver's link carries less, or has
        not been shown to (RateController.sending_bps). ``congested_only``: the estimate
        alone, where its reports have shown a queue or loss: not its cautious start, which
        the datagrams' packing need not follow."""
        rates = [
            p.controller.rate_bps if congested_only else p.controller.sending_bps
            for p in self.live(now)
            if p.controller.decreases or not congested_only
        ]
        return min([most, *rates])

    def on_this_machine(self, now: float) -> bool:
        """Whether every live receiver is on this machine (a loopback address): there the
        headers cost no link anything, so frames need not share a datagram (each would wait
        for the next, 33 ms at 30 fps) and the budget need not count them (Bundler)."""
        live = self.live(now)
        return bool(live) and all(_is_loopback(p.address) for p in live)

    def send_to(self, identity: bytes, bundle: bytes, now: float) -> bool:
        """Seal ``bundle`` to the receiver ``identity`` alone, if its path is live."""
        peer = self._by_identity.get(identity)
        return peer is not None and peer.live(now) and self._seal_to(peer, bundle, now)

    def send(self, bundle: bytes, now: float) -> int:
        """Seal ``bundle`` to every live receiver; how many it went to."""
        sent = 0
        for peer in self.live(now):
            sent += self._seal_to(peer, bundle, now)
        return sent

    def _seal_to(
        self, peer: _Receiver, bundle: bytes, now: float, to: tuple[str, int] | None = None
    ) -> bool:
        address = to or peer.address
        if address is None:
            return False
        index = peer.sealer.index
        if not self._sendto(peer.sealer.seal(bundle), address):
            return False
        peer.controller.on_sent(index, now)
        return True


class Bundler:
    """What goes in the sender's next datagram, and when it leaves.

    Updates handed to :meth:`add` wait for the end of the frame that made them; every
    ``frames_per_datagram`` frames (from the budget: :func:`frames_per_datagram`) all that waits
    leaves in one datagram (more only if it does not fit in MAX_DATAGRAM bytes). REM patches
    (:meth:`add_patch`) leave as the budget allows: a token bucket of the budget pays for the
    rest first, and what is left carries patches, whole or in fragments. A bulk message
    (:meth:`add_bulk`: the snapshot's full images after its draft) takes only what the
    patches leave: the eyes keep moving while it crosses a thin link.

    ``redundant``: on a lossy link each datagram carries the last one's updates again (not its
    patches), as RFC 2198's redundant audio does, so one lost datagram loses nothing; the
    receiver drops the second copies. ``losing``: the receiver's reports show loss now (the
    repeats also run at a call's start, before any report): fewer frames share a datagram, and
    each carries the frame packets of the datagram before the last too, so two lost in a row
    break no chain (the sound's Opus conceals a gap): at 5% loss one pair in 400 datagrams
    did, and the keyframe it then asked for froze the picture 200-233 ms.
    ``hurry``: ask for reports at the faster beat (a Hurry element every HURRY_EVERY_S).
    """

    def __init__(self, fps: float) -> None:
        self.fps = fps
        self._due: list[bytes] = []
        self._last_due: list[bytes] = []
        # The frame packets among those due, the last datagram's and the one's before it.
        self._due_frames: list[bytes] = []
        self._last_frames: list[bytes] = []
        self._older_frames: list[bytes] = []
        self.redundant = False
        self.losing = False
        self.hurry = False
        self._hurried = -math.inf
        self._patches: deque[tuple[int, bytes, int]] = deque()  # message, packet, offset sent
        self._bulk: deque[tuple[int, bytes, int]] = deque()  # the same, after the patches
        self._message = 0
        self._frames = 0
        self._tokens = 0.0
        self._filled: float | None = None
        self.patch_bytes_waiting = 0
        self.bulk_bytes_waiting = 0
        self.k = 1
        #: Bytes each datagram costs the budget besides its bundle: none to a receiver on this
        #: machine (SenderMediaPath.on_this_machine).
        self.header_bytes = DATAGRAM_COST
        #: What leaves whatever the budget (frames, sound, heartbeats), bits per second: an
        #: average over about a second.
        self.due_bps = 0.0
        self._due_bytes = 0
        self._due_since: float | None = None

    def add(self, data: bytes, frame: bool = False) -> None:
        """An update due with this frame; ``frame``: a KeyFrame or a DeltaFrame (the ones
        repeated twice while ``losing``)."""
        self._due.append(data)
        self._due_bytes += len(data)
        if frame:
            self._due_frames.append(data)

    def add_patch(self, data: bytes) -> None:
        self._patches.append((self.number(data), data, 0))
        self.patch_bytes_waiting += len(data)

    def add_bulk(self, data: bytes) -> None:
        self._bulk.append((self.number(data), data, 0))
        self.bulk_bytes_waiting += len(data)

    def drop_bulk(self) -> None:
        """Forget the bulk messages not sent yet (a Bye: nothing after it is taken)."""
        self._bulk.clear()
        self.bulk_bytes_waiting = 0

    def number(self, data: bytes) -> int:
        """The next message number, for ``data`` sent in Fragments (:func:`fragments` too)."""
        if len(data) > MAX_REASSEMBLED:
            raise ValueError(f"a {len(data)}-byte patch is too large for a datagram's fragments")
        self._message = (self._message + 1) % 256
        return self._message

    def holds(self, data: bytes) -> bool:
        """Whether ``data`` (handed to :meth:`add_patch` or :meth:`add_bulk`) has not all
        left yet."""
        return any(packet is data for _, packet, _ in (*self._patches, *self._bulk))

    def end_frame(
        self, now: float, budget_bps: float, packing_bps: float | None = None
    ) -> list[bytes]:
        """The bundles to send now that a frame is done (none until the k-th frame):
        ``packing_bps`` (default ``budget_bps``) sets how many frames share a datagram,
        ``budget_bps`` what the patches may take."""
        self._frames += 1
        if self._due_since is None:
            self._due_since = now
        elif now - self._due_since >= 1.0:
            rate = self._due_bytes * 8.0 / (now - self._due_since)
            self.due_bps = rate if self.due_bps == 0 else 0.5 * (self.due_bps + rate)
            self._due_bytes, self._due_since = 0, now
        packing = budget_bps if packing_bps is None else packing_bps
        self.k = frames_per_datagram(packing, self.fps, self.losing, self.header_bytes)
        if self._frames < self.k:
            return []
        self._frames = 0
        return self.flush(now, budget_bps)

    def flush(self, now: float, budget_bps: float) -> list[bytes]:
        """Everything due, now, and what the budget allows of the patches."""
        if not self._due and not self._patches and not self._bulk:
            return []
        rate = min(budget_bps, 1e9) / 8.0  # a Bye's flush pays whatever it costs
        depth = rate * min(BUCKET_S, self.k / self.fps)
        if self._filled is not None:
            self._tokens = min(depth, self._tokens + rate * (now - self._filled))
        self._filled = now
        out: list[bytes] = []
        elements: list[bytes] = []
        size = 0
        if self.hurry and now - self._hurried >= HURRY_EVERY_S:
            self._hurried = now
            elements.append(_HURRY_ELEMENT)
            size += element_size(len(_HURRY_ELEMENT))
        again = []
        if self.redundant:
            again = self._last_due
            if self.losing:
                again = self._older_frames + again
            if _size(again + self._due) > MAX_DATAGRAM - OVERHEAD:
                again = self._last_due
            if _size(again + self._due) > MAX_DATAGRAM - OVERHEAD:
                again = []  # a repeat never takes a datagram of its own
        for element in again + self._due:
            need = element_size(len(element))
            if elements and size + need > MAX_DATAGRAM - OVERHEAD:
                out.append(pack(elements))
                elements, size = [], 0
            elements.append(element)
            size += need
        self._last_due, self._due = self._due, []
        self._older_frames, self._last_frames = self._last_frames, self._due_frames
        self._due_frames = []
        spend = size + self.header_bytes * (len(out) + 1)
        room = int(min(MAX_DATAGRAM - OVERHEAD - size, self._tokens - spend))
        # A patch that the bucket lacks at most its depth for goes whole, once a datagram, the
        # bucket then owing it: sliced, an eye's 150 bytes paid a Fragment's header twice
        # (0.4 kbit/s of a clean link's 13). The next datagrams carry no patch until it is paid.
        # Not while the rate control has something to follow (``hurry``: the call's first
        # seconds, a queue, a cut): there the bigger datagrams queued on a 24 kbit/s link.
        borrow = 0 if self.hurry else int(min(depth, MAX_DATAGRAM - OVERHEAD - size - max(room, 0)))
        chunks, room, taken = _serve(self._patches, room, borrow)
        self.patch_bytes_waiting -= taken
        if not self._patches:
            bulk, room, taken = _serve(self._bulk, room, 0)
            self.bulk_bytes_waiting -= taken
            chunks += bulk
        elements += chunks
        spend += _size(chunks)
        out.append(pack(elements))
        self._tokens -= spend
        return out


def fragment_room(room: int) -> int:
    """Bytes of a message one Fragment carries in a bundle's ``room`` bytes: less its header
    and its element's length (3 bytes at most)."""
    return room - FRAGMENT_HEADER - 3


def fragments(data: bytes, message: int) -> list[bytes]:
    """``data`` as the Fragments of message ``message``, one bundle each, as full as a
    datagram takes them."""
    room = fragment_room(MAX_DATAGRAM - OVERHEAD)
    return [
        pack([bytes(Fragment(message, len(data), offset, data[offset : offset + room]))])
        for offset in range(0, len(data), room)
    ]


def _size(elements: list[bytes]) -> int:
    """Bytes ``elements`` take in a bundle."""
    return sum(element_size(len(e)) for e in elements)


def _serve(
    queue: deque[tuple[int, bytes, int]], room: int, borrow: int
) -> tuple[list[bytes], int, int]:
    """What of ``queue``'s messages (message number, packet, offset sent) fits in ``room``
    bytes, in order: whole elements, or Fragments of what does not fit; one message may go
    whole by ``borrow`` bytes more. (elements, room left, packet bytes taken.)"""
    chunks: list[bytes] = []
    total = 0
    while queue:
        message, packet, offset = queue[0]
        if offset == 0 and element_size(len(packet)) <= room + borrow:
            chunk, taken = packet, len(packet)
            room += borrow
            borrow = 0
        elif room > FRAGMENT_HEADER + 16:
            taken = min(len(packet) - offset, fragment_room(room))
            part = packet[offset : offset + taken]
            chunk = bytes(Fragment(message, len(packet), offset, part))
        else:
            break
        if offset + taken >= len(packet):
            queue.popleft()
        else:
            queue[0] = (message, packet, offset + taken)
        total += taken
        chunks.append(chunk)
        room -= element_size(len(chunk))
    return chunks, room, total


# --- the receiver's end -------------------------------------------------------------------------


class ReceiverMediaPath(_Path):
    """The receiver's UDP socket: opens the sender's datagrams, sends reports and hellos."""

    def __init__(self, host: str, port: int, bind: bool) -> None:
        super().__init__(host, port, bind, "receiver")
        self._sealer: Sealer | None = None
        self._opener: Opener | None = None
        self._keyed_at = -math.inf
        self._peer: tuple[str, int] | None = None
        self.last_heard = -math.inf
        self._last_hello = -math.inf
        self._last_report = -math.inf
        self._hurried_until = -math.inf
        self._reassembly = Reassembly()
        self._highest = 0
        self._arrival_ms = 0
        self._received = 0
        self._received_bytes = 0
        self._live_told = False
        self._fallback_told = False
        self.malformed = 0  # elements of authentic datagrams that were malformed

    @property
    def keyed(self) -> bool:
        return self._opener is not None

    def take_key(self, key: MediaKey, now: float) -> None:
        """The sender's key for this join (each join brings a new one)."""
        self._sealer = Sealer(key.secret, RECEIVER_TO_SENDER, key.key_id)
        self._opener = Opener(key.secret, SENDER_TO_RECEIVER, key.key_id)
        self._keyed_at = now
        self._peer = None
        self.last_heard = -math.inf
        self._reassembly = Reassembly()
        self._received = self._received_bytes = 0
        self._live_told = self._fallback_told = False

    def live(self, now: float) -> bool:
        return now - self.last_heard < PATH_TIMEOUT_S

    def joined(self, now: float) -> None:
        """The snapshot has come: a path that never opened is timed from now (the sender's
        first datagrams crossed a thin link behind it)."""
        if self.last_heard == -math.inf:
            self._keyed_at = now

    def read(self, now: float, now_ms: int) -> list[bytes]:
        """The version-2 packets in the datagrams that came (fragments put together)."""
        out: list[bytes] = []
        if self._opener is None:
            return out
        for _ in range(_MAX_READ):
            got = self._recv()
            if got is None:
                break
            data, address, age = got
            opened = self._open(self._opener, data)
            if opened is None:
                continue
            index, elements = opened
            fresh = not self.live(now)
            self._peer, self.last_heard = address, now
            if index == self._opener.window.highest:  # a late one names no newer datagram
                self._highest, self._arrival_ms = index, now_ms - round(age * 1000)
            self._received += 1
            self._received_bytes += len(data)
            if fresh:
                self._opened(now)
                # The sender's rate control knows nothing yet: the faster beat until it says.
                self._hurried_until = now + HURRY_HOLD_S
            for element in elements:
                if element == _HURRY_ELEMENT:
                    self._hurried_until = now + HURRY_HOLD_S
                    continue
                packet = self._element(element)
                if packet is not None:
                    out.append(packet)
        return out

    def _element(self, element: bytes) -> bytes | None:
        kind = element[0]
        if kind >> 4 == PROTOCOL_VERSION:
            return element
        if kind == FRAGMENT:
            try:
                return self._reassembly.add(Fragment.parse(element))
            except BundleError:
                pass
        self.malformed += 1
        return None

    def _opened(self, now: float) -> None:
        if not self._live_told or self._fallback_told:
            logger.info("media: datagrams (UDP) from the sender at %s:%d", *self._peer_or())
        self._live_told, self._fallback_told = True, False
        # At once, not at the next report: the sender learns the path works both ways, and
        # a draft waiting for it leaves (docs/protocol.md 8.7).
        self._send(b"")

    def _peer_or(self) -> tuple[str, int]:
        return self._peer or self.dest or ("?", 0)

    @property
    def patches_lost(self) -> int:
        return self._reassembly.lost

    def service(self, now: float, now_ms: int) -> None:
        """Hellos while the path is not open; reception reports while it is."""
        if self._sealer is None:
            return
        if self.live(now):
            interval = HURRIED_REPORT_INTERVAL_S if now < self._hurried_until else REPORT_INTERVAL_S
            if now - self._last_report >= interval:
                # On the interval's beat, not from when the loop came by (it comes by when a
                # datagram does: 3.5 reports a second), and never two at once after a stall.
                self._last_report = max(self._last_report + interval, now - interval / 2)
                report = Report(self._highest, self._arrival_ms, self._received,
                                self._received_bytes)  # fmt: skip
                self._send(pack([bytes(report)]))
            return
        since = now - max(self._keyed_at, self.last_heard)
        if since >= PATH_TIMEOUT_S and not self._fallback_told:
            self._fallback_told = True
            logger.warning(
                "media: no datagram from the sender for %g s (UDP blocked?): media over ZeroMQ/TCP",
                PATH_TIMEOUT_S,
            )
        interval = HELLO_INTERVAL_S if since < PATH_TIMEOUT_S else REPROBE_INTERVAL_S
        if now - self._last_hello >= interval:
            self._last_hello = now
            self._send(b"")

    def send_request(self, request: KeyframeRequest, now: float) -> bool:
        """A keyframe request in a datagram of its own, where the path is live."""
        if self._sealer is None or not self.live(now):
            return False
        self._send(pack([bytes(request)]))
        return True

    def _send(self, bundle: bytes) -> None:
        address = self._peer or self.dest
        if self._sealer is not None and address is not None:
            self._sendto(self._sealer.seal(bundle), address)
