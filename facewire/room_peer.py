"""The other participants of a room, as this one receives them.

:class:`RoomReceiver` takes every message the link delivers: it opens it (protocol/sframe.py),
and a media bundle from someone new first fetches that one's snapshot from the room's
bucket (the Clone pattern: subscribed first, then the state, then the updates), builds a
:class:`Peer` (the two-party receiver's FaceDecoder, and its CallSound: facewire/room_sound.py)
and asks that sender for a keyframe on its own control subject. That is done on a thread of
the newcomer's own (facewire/room_join.py), so the others' pictures go on meanwhile. A peer
leaves on its Bye, or when nothing of it came for PEER_GONE_S; its recording then gets its
voice.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from facewire.protocol import subjects
from facewire.protocol.bundle import FRAGMENT, BundleError, Fragment, Reassembly, unpack
from facewire.protocol.channels import ChainBroken
from facewire.protocol.clock import now_us
from facewire.protocol.constants import PROTOCOL_VERSION
from facewire.protocol.packets import (
    AudioFrame,
    Bye,
    DeltaFrame,
    Heartbeat,
    KeyFrame,
    KeyframeRequest,
    PacketError,
    Refresh,
    RemPatch,
    Snapshot,
    decode,
)
from facewire.protocol.sender_keys import KeyUnavailable, SenderKeys
from facewire.protocol.sframe import Header, Opener, RoomKey, Sealer, SFrameError, kid_is_of
from facewire.room_join import Joining

if TYPE_CHECKING:
    from facewire.room_sound import RoomSound

logger = logging.getLogger(__name__)

#: A participant silent this long has left (it heartbeats at least every second).
PEER_GONE_S = 2.5
#: Keyframe requests to one sender, at most one per this long.
KEYFRAME_RETRY_S = 0.5
#: A sender whose messages do not open is looked at again after this long (it may rejoin).
LOCKED_RETRY_S = 5.0
#: A snapshot that was not in the bucket (or the bucket did not answer) is asked for again
#: after this long, not at each of that sender's messages.
SNAPSHOT_RETRY_S = 0.5
#: The longest gap in a recording filled by holding the last picture (frames).
MAX_HOLD_FRAMES = 60
#: A wait this long between two decoded frames of a peer is kept in its figures (a freeze;
#: a still face sends a frame a second, a moving one 15-30), at most MAX_FREEZES of them.
FREEZE_MS = 200.0
MAX_FREEZES = 1000
#: Pictures kept to tell the sound how long after capture a face is shown (it uses the last 30).
SHOWN_KEPT = 60
SNAPSHOT, MEDIA, CONTROL = b"s", b"m", b"c"
#: Put in the inbox to wake the receiving loop (a newcomer is ready).
_WAKE = ("", b"", 0)


def _summary(values: list[float]) -> dict[str, float]:
    if not values:
        return {}
    a = np.asarray(values)
    return {
        "p50": round(float(np.percentile(a, 50)), 2),
        "p99": round(float(np.percentile(a, 99)), 2),
        "max": round(float(a.max()), 2),
    }


def _nats_bytes(subject: str, data: bytes) -> int:
    """A message's bytes on the NATS connection: ``MSG subject sid size\\r\\n``, the payload,
    ``\\r\\n`` (a one-digit subscription id; TCP/IP headers not counted)."""
    return len(f"MSG {subject} 1 {len(data)}\r\n") + len(data) + 2


class Peer:
    """One other participant: its decoder, its sound, its recording."""

    def __init__(
        self,
        name: str,
        kid: int,
        snapshot: Snapshot,
        record: Path | None,
        gallery: Any = None,
        sound: RoomSound | None = None,
    ) -> None:
        from facewire.receiver.decoder import FaceDecoder
        from facewire.receiver.interpolation import Painter

        self.name = name
        self.kid = kid
        self.snapshot = snapshot
        self.decoder = FaceDecoder(snapshot)
        self.gallery = gallery
        # Pictures are drawn only for someone: a recording or the gallery.
        drawn = record is not None or gallery is not None
        self.painter = Painter(self.decoder) if drawn else None
        self.record = record
        self.recorder: Any = None
        if record is not None:
            from facewire.receiver.recording import BackgroundRecorder

            self.recorder = BackgroundRecorder(
                record, snapshot.width, snapshot.height, snapshot.fps
            )
        self.reassembly = Reassembly()
        self.last_heard = time.monotonic()
        self.next_seq: int | None = None  # the recording's next frame
        self.last_picture: np.ndarray | None = None
        self.last_request = -float("inf")
        self.chain_broken = True  # until the keyframe that starts the chain
        self.sound = sound
        # (shown µs, captured µs) of the latest pictures: the voice waits for the face.
        self.shown: list[tuple[int, int]] = []
        self.audio = sound.for_peer(name, self.shown, snapshot.fps) if sound is not None else None
        self.first_seq: int | None = None  # the sender's frame the recording starts with

    def new_scene(self, snapshot: Snapshot) -> None:
        """Draw from ``snapshot`` on: the sender cut to a new scene, which it sends in a
        session of its own (docs/protocol.md 8.9). The recording, the sound and the gallery's
        tile go on; the last picture stays until the new session's keyframe. ValueError (and
        nothing changed) for a snapshot this decoder cannot take, or of another frame size
        (a recording has one)."""
        from facewire.receiver.decoder import FaceDecoder
        from facewire.receiver.interpolation import Painter

        size = (snapshot.width, snapshot.height)
        if size != (self.snapshot.width, self.snapshot.height):
            raise ValueError(f"a new scene of {size[0]}x{size[1]}, not its first one's size")
        decoder = FaceDecoder(snapshot)
        self.decoder.close()
        self.snapshot, self.decoder = snapshot, decoder
        if self.painter is not None:
            self.painter = Painter(decoder)
        self.chain_broken = True

    def take(self, packet: object, figures: PeerFigures, arrival_us: int) -> bool:
        """Decode (and record, and play) one packet; True when a keyframe should be asked
        for. ``arrival_us``: when its message came."""
        if isinstance(packet, (KeyFrame, DeltaFrame)):
            try:
                values = self.decoder.decode(packet)
            except ChainBroken as exc:
                logger.debug("%s: %s", self.name, exc)
                figures.chain_breaks += 1
                self.chain_broken = True
                return True
            except PacketError as exc:
                logger.debug("%s: dropped frame packet: %s", self.name, exc)
                figures.malformed += 1
                return True
            self.chain_broken = False
            now = now_us()
            figures.frames += 1
            latency_ms = (now - values.capture_us) / 1000.0
            figures.latency_ms.append(latency_ms)
            figures.arrival_ms.append((arrival_us - values.capture_us) / 1000.0)
            if figures.last_frame_us is not None:
                gap_ms = (now - figures.last_frame_us) / 1000.0
                figures.max_gap_ms = max(figures.max_gap_ms, gap_ms)
                if gap_ms >= FREEZE_MS and len(figures.freezes) < MAX_FREEZES:
                    figures.freezes.append((figures.last_frame_us, round(gap_ms, 1)))
            figures.last_frame_us = now
            # The recording's frame this picture becomes places the voice in the recording.
            index = values.seq if self.recorder is None else self._hold(values.seq)
            if self.painter is not None:
                picture = self._record(values)
                if self.gallery is not None:  # it waits there for its voice
                    self.gallery.show(self.name, picture, values.capture_us)
            if self.audio is not None:
                self.shown.append((now_us(), values.capture_us))
                del self.shown[:-SHOWN_KEPT]
                self.audio.frame(index, values.capture_us, arrival_us)
        elif isinstance(packet, (RemPatch, Refresh)):
            self.decoder.offer(packet)
        elif isinstance(packet, AudioFrame):
            figures.audio_packets += 1
            if self.audio is not None and self.sound is not None:
                self.sound.heard()
                self.audio.push(packet, arrival_us)
        return False

    def _hold(self, seq: int) -> int:
        """Hold the last picture over the frames that did not come before ``seq`` (up to
        MAX_HOLD_FRAMES); the recording's index ``seq``'s picture gets."""
        assert self.recorder is not None
        if self.first_seq is None:
            self.first_seq = seq
        if self.next_seq is not None and self.last_picture is not None:
            gap = min(seq - self.next_seq, MAX_HOLD_FRAMES)
            for _ in range(max(0, gap)):  # frames with no packet hold the last picture
                self.recorder.write(self.last_picture)
        return int(self.recorder.frames)

    def said_bye(self, seq: int) -> None:
        """The sender's stream ended before its frame ``seq``: the recording holds the last
        picture to there (frames a still face did not send), as a two-party one does."""
        if self.recorder is not None and self.last_picture is not None:
            self._hold(seq)

    def _record(self, values: Any) -> np.ndarray:
        assert self.painter is not None
        picture = self.painter.exact(values)
        if self.recorder is None:
            return picture
        self.recorder.write(picture)
        self.last_picture = picture
        self.next_seq = values.seq + 1
        return picture

    def close(self) -> None:
        """Stop decoding (on the receiving thread: the renderer's GL context is its own)."""
        self.decoder.close()

    def finish(self, play_out: bool) -> dict[str, Any]:
        """Play out what sound is buffered (when the peer said bye), stop it, finish the
        recording with its voice muxed in; the sound's figures. Any thread."""
        sound: dict[str, Any] = {}
        try:
            if self.audio is not None and play_out:
                self.audio.play_out()
            if self.recorder is not None:
                self.recorder.close()
        finally:
            if self.audio is not None:
                sound = self.audio.finish(self.record)
        return sound


class PeerFigures:
    """What this participant measured of one other, over all of its sessions."""

    def __init__(self) -> None:
        self.frames = 0
        self.latency_ms: list[float] = []
        # Capture to the arrival of its message at this participant's link: the relay's
        # share (and the bundling's), without the wait in the inbox and the decoding.
        self.arrival_ms: list[float] = []
        self.sealed_bytes = 0
        self.nats_bytes = 0
        self.messages = 0
        self.first_us: int | None = None
        self.last_us = 0
        self.keyframe_requests = 0
        self.chain_breaks = 0
        self.malformed = 0
        self.audio_packets = 0
        self.sessions = 0
        self.scenes = 0  # new scenes it went on to within a session (docs/protocol.md 8.9)
        self.left: str | None = None
        self.last_frame_us: int | None = None
        self.max_gap_ms = 0.0  # the longest wait between two decoded frames (a freeze)
        self.freezes: list[tuple[int, float]] = []  # (from µs, ms) of waits over FREEZE_MS
        self.sound: dict[str, Any] = {}  # receiver/audio.py's AudioReport, sessions added
        self.recorded_from: int | None = None  # the sender's frame its recording starts with

    def add_sound(self, session: dict[str, Any]) -> None:
        """A session's sound figures: counts are added; the latency, the offset to the face
        and the sink are the latest session's."""
        for key, value in session.items():
            if isinstance(value, int) and key in self.sound:
                self.sound[key] += value
            else:
                self.sound[key] = value

    def as_dict(self) -> dict[str, Any]:
        span_s = (self.last_us - (self.first_us or self.last_us)) / 1e6

        def kbps(n: int) -> float:
            return round(n * 8 / span_s / 1000, 2) if span_s > 0 else 0.0

        return {
            "frames": self.frames,
            "latency_ms": _summary(self.latency_ms),
            "arrival_ms": _summary(self.arrival_ms),
            "kbps": {"sealed": kbps(self.sealed_bytes), "nats": kbps(self.nats_bytes)},
            "messages": self.messages,
            "bytes": {"sealed": self.sealed_bytes, "nats": self.nats_bytes},
            "max_gap_ms": round(self.max_gap_ms, 1),
            "freezes": self.freezes,
            "sessions": self.sessions,
            "scenes": self.scenes,
            "keyframe_requests": self.keyframe_requests,
            "chain_breaks": self.chain_breaks,
            "malformed": self.malformed,
            "audio_packets": self.audio_packets,
            "sound": self.sound,
            "recorded_from": self.recorded_from,
            "left": self.left,
        }


class RoomReceiver:
    """Everything that arrives, opened and handed to the right peer (one thread runs it)."""

    def __init__(
        self,
        key: RoomKey | SenderKeys,
        name: str,
        get_snapshot: Callable[[str], bytes | None],
        publish: Callable[[str, bytes], None],
        sealer: Sealer,
        notify: Callable[[str], None],
        record_dir: Path | None = None,
        on_keyframe_request: Callable[[KeyframeRequest], None] | None = None,
        gallery: Any = None,
        sound: RoomSound | None = None,
    ) -> None:
        self.key = key
        self.name = name
        self.get_snapshot = get_snapshot
        self.publish = publish
        self.sealer = sealer  # this participant's own (its keyframe requests are sealed too)
        self.notify = notify
        self.record_dir = record_dir
        self.on_keyframe_request = on_keyframe_request
        self.gallery = gallery
        self.sound = sound  # None: the peers' sound is neither played nor recorded
        self.inbox: queue.Queue[tuple[str, bytes, int]] = queue.Queue()
        self.opener = Opener()
        self.peers: dict[str, Peer] = {}
        self.joining: dict[str, Joining] = {}  # newcomers whose decoders are being built
        self.figures: dict[str, PeerFigures] = {}
        self.locked: dict[str, float] = {}  # name -> when its messages last failed to open
        self.asked: dict[str, float] = {}  # name -> when its snapshot was last read
        self.rejected: Counter[str] = Counter()  # messages that did not open, per sender
        self.told: set[str] = set()
        self.finishing: list[threading.Thread] = []  # peers' sound and recordings
        self.finish_errors: list[Exception] = []

    def deliver(self, subject: str, data: bytes, arrival_us: int) -> None:
        """The link's callback (its thread): queue only."""
        self.inbox.put((subject, data, arrival_us))

    def run_once(self, timeout_s: float) -> None:
        """Handle what came within ``timeout_s`` (less when a picture of the gallery is due
        sooner), then drop peers gone silent."""
        if self.gallery is not None:
            timeout_s = min(timeout_s, self.gallery.wait_s())
        try:
            item: tuple[str, bytes, int] | None = self.inbox.get(timeout=timeout_s)
        except queue.Empty:
            item = None
        while item is not None:
            if item is not _WAKE:
                self._handle(*item)
            try:
                item = self.inbox.get_nowait()
            except queue.Empty:
                item = None
        for joining in [j for j in self.joining.values() if j.done.is_set()]:
            self._joined(joining)
        if self.gallery is not None:
            self.gallery.tick()
        now = time.monotonic()
        for peer in list(self.peers.values()):
            if now - peer.last_heard > PEER_GONE_S:
                self._drop(peer, f"silent for {PEER_GONE_S:g} s")

    def _handle(self, subject: str, data: bytes, arrival_us: int) -> None:
        try:
            kind, sender, _ = subjects.parse(subject)
            subjects.check_name(sender, "participant")
        except ValueError as exc:
            logger.debug("%s", exc)
            return
        if sender == self.name:
            return
        if kind == "c":
            self._control(sender, data)
            return
        figures = self.figures.setdefault(sender, PeerFigures())
        peer = self._peer(subject, sender, data, arrival_us)
        if peer is None:
            return
        try:
            bundle = self.opener.open(data, self.key.metadata(sender, MEDIA))
        except SFrameError as exc:
            self._rejected(sender, exc)
            return
        peer.last_heard = time.monotonic()
        figures.messages += 1
        figures.sealed_bytes += len(data)
        figures.nats_bytes += _nats_bytes(subject, data)
        figures.first_us = figures.first_us or arrival_us
        figures.last_us = arrival_us
        if self.gallery is not None:
            self.gallery.report.bytes_received[sender] = figures.nats_bytes
        want_keyframe = False
        for packet in self._packets(peer, bundle, figures):
            if isinstance(packet, Bye):
                peer.said_bye(packet.seq)
                self._drop(peer, "said bye", play_out=True)
                return
            if (
                isinstance(packet, (Heartbeat, KeyFrame))
                and packet.session_id != peer.snapshot.session_id
            ):
                # Its new scene (a heartbeat says it first, and ends its message). Drawn with
                # this model it would be the old scene with the new face on it: its messages
                # wait until its snapshot is read (a keyframe's, the keyframe among them).
                self._new_scene(peer, packet.session_id)
                if isinstance(packet, KeyFrame):
                    self.joining[sender].backlog.append((subject, data, arrival_us))
                return
            if not isinstance(packet, Heartbeat):
                want_keyframe |= peer.take(packet, figures, arrival_us)
        if want_keyframe or peer.chain_broken:
            self._ask_keyframe(peer, figures)

    def _peer(self, subject: str, sender: str, data: bytes, arrival_us: int) -> Peer | None:
        """The peer ``data`` comes from; None while its messages cannot be opened, or while
        it is being joined (a new one, or a new run of one: another KID), its messages kept
        for when it is ready."""
        try:
            kid = Header.parse(data)[0].kid
        except SFrameError as exc:
            self._rejected(sender, exc)
            return None
        peer = self.peers.get(sender)
        joining = self.joining.get(sender)
        if peer is not None and peer.kid == kid and (joining is None or joining.session is None):
            return peer
        if joining is not None:
            if joining.kid == kid:
                joining.backlog.append((subject, data, arrival_us))
                if peer is not None:  # its new scene is being joined: it is not silent
                    peer.last_heard = time.monotonic()
            return None
        if not kid_is_of(kid, sender):
            self._rejected(sender, SFrameError(f"KID {kid:#x} is not {sender}'s"))
            return None
        now = time.monotonic()
        if now - self.locked.get(sender, -LOCKED_RETRY_S) < LOCKED_RETRY_S:
            return None
        if now - self.asked.get(sender, -SNAPSHOT_RETRY_S) < SNAPSHOT_RETRY_S:
            return None
        self.asked[sender] = now
        try:
            base_key = self.key.base_key(sender, kid)
        except SFrameError as exc:  # a peer's key this one has no box for (sender_keys.py)
            self.locked[sender] = now
            self._rejected(sender, exc)
            return None
        if peer is not None:
            self._drop(peer, "restarted")
        self.opener.add_key(kid, base_key)
        record = None
        if self.record_dir is not None:
            # A later session (the sender restarted) gets a file of its own, NAME.2.mp4 and
            # on: the one before may still be getting its sound. Names have no dots.
            again = self.figures[sender].sessions
            record = self.record_dir / (f"{sender}.{again + 1}.mp4" if again else f"{sender}.mp4")
        joining = Joining(sender, kid, record, self._build, self._wake)
        joining.backlog.append((subject, data, arrival_us))
        self.joining[sender] = joining
        return None

    def _new_scene(self, peer: Peer, session: int) -> None:
        """``peer``'s packets name ``session``: its new scene's snapshot is read as a
        newcomer's is, and its messages wait for it (:meth:`_joined` gives it to ``peer``)."""
        joining = Joining(peer.name, peer.kid, peer.record, self._build, self._wake, session)
        self.joining[peer.name] = joining

    def _wake(self) -> None:
        self.inbox.put(_WAKE)

    def _build(self, joining: Joining) -> None:
        """On ``joining``'s thread: read and open its snapshot (a wait on the relay that
        must not hold the others' pictures up) and ask for the keyframe; the receiving loop
        builds the decoder (:meth:`_joined`). Built here too, one room's call once waited
        90 s for a newcomer that never came, with GL used on three threads at once."""
        name = joining.name
        sealed = self.get_snapshot(name)
        if sealed is None:
            return
        snapshot = decode(self.opener.open(sealed, self.key.metadata(name, SNAPSHOT), False))
        if not isinstance(snapshot, Snapshot):
            raise PacketError(f"expected a Snapshot, got {type(snapshot).__name__}")
        if joining.session is not None and snapshot.session_id != joining.session:
            # The sender puts a new scene's snapshot in the bucket before it says so: this
            # is an older one (or a forged message's session).
            raise PacketError(
                f"the bucket has session {snapshot.session_id}, not the {joining.session} "
                "its messages name"
            )
        self._request_keyframe(name, snapshot.seq)
        joining.asked_keyframe = True
        joining.snapshot = snapshot

    def _joined(self, joining: Joining) -> None:
        """``joining`` is done: the peer takes its place and its messages so far are decoded,
        or what went wrong is said (its messages are dropped; it is tried again later)."""
        name = joining.name
        del self.joining[name]
        exc, peer = joining.error, None
        shown = self.peers.get(name) if joining.session is not None else None
        if shown is not None:
            self._scene_joined(shown, joining)
            return
        if exc is None and joining.snapshot is not None:
            try:
                peer = Peer(
                    name, joining.kid, joining.snapshot, joining.record, self.gallery, self.sound
                )
            except ValueError as refused:  # said below as the read's own errors are
                exc = refused
        if isinstance(exc, SFrameError):
            self.locked[name] = time.monotonic()
            self._rejected(name, exc)
            return
        if isinstance(exc, PacketError):
            self.locked[name] = time.monotonic()
            logger.info("%s's snapshot: %s", name, exc)
            return
        if isinstance(exc, ValueError):  # a snapshot this decoder cannot take (another rig)
            self.locked[name] = time.monotonic()
            self.notify(f"{name} cannot be shown: {exc}")
            return
        if exc is not None:
            raise exc
        if peer is None:
            logger.info("%s sends but has no snapshot in the room's bucket yet", name)
            return
        figures = self.figures[name]
        if joining.asked_keyframe:
            figures.keyframe_requests += 1
            peer.last_request = time.monotonic()  # its keyframe is on its way
        if self.gallery is not None and peer.audio is not None:
            self.gallery.joined(name, peer.audio.delay_us)  # each picture with its voice
        elif self.gallery is not None:
            self.gallery.joined(name)
        self.peers[name] = peer
        figures.sessions += 1
        self.locked.pop(name, None)
        snapshot = peer.snapshot
        self.notify(
            f"{name} joined: {snapshot.width}x{snapshot.height} at {snapshot.fps:g} fps"
            + (f", recording to {peer.record}" if peer.record is not None else "")
        )
        for item in joining.backlog:
            self._handle(*item)

    def _scene_joined(self, peer: Peer, joining: Joining) -> None:
        """``peer``'s new scene was read: drawn from now on, its messages so far decoded. If
        it cannot be, the peer leaves and those messages join it again as a newcomer (with
        the bucket's snapshot then, in a recording of its own)."""
        exc, snapshot = joining.error, joining.snapshot
        if exc is not None and not isinstance(exc, (SFrameError, PacketError, ValueError)):
            raise exc
        if exc is None and snapshot is None:
            exc = PacketError("the bucket has no snapshot of it")
        if exc is None and snapshot is not None:
            try:
                peer.new_scene(snapshot)
            except ValueError as refused:
                exc = refused
        if exc is None:
            figures = self.figures[peer.name]
            figures.scenes += 1
            if joining.asked_keyframe:
                figures.keyframe_requests += 1
                peer.last_request = time.monotonic()  # its keyframe is on its way
            from facewire.receiver.decoder import new_scene_news

            self.notify(f"{peer.name}: {new_scene_news(peer.snapshot)}")
        else:
            logger.info("%s's new scene: %s", peer.name, exc)
            self._drop(peer, f"its new scene cannot be shown: {exc}")
            self.asked.pop(peer.name, None)  # its next message is read as a newcomer's
        for item in joining.backlog:
            self._handle(*item)

    def _packets(self, peer: Peer, bundle: bytes, figures: PeerFigures) -> list[object]:
        out: list[object] = []
        try:
            elements = list(unpack(bundle))
        except BundleError:
            figures.malformed += 1
            return out
        for element in elements:
            data: bytes | None = element
            if element[0] == FRAGMENT:
                try:
                    data = peer.reassembly.add(Fragment.parse(element))
                except BundleError:
                    data = None
                    figures.malformed += 1
            elif element[0] >> 4 != PROTOCOL_VERSION:
                data = None
                figures.malformed += 1
            if data is None:
                continue
            try:
                out.append(decode(data))
            except PacketError as exc:
                logger.debug("%s: %s", peer.name, exc)
                figures.malformed += 1
        return out

    def _ask_keyframe(self, peer: Peer, figures: PeerFigures) -> None:
        now = time.monotonic()
        if now - peer.last_request < KEYFRAME_RETRY_S:
            return
        peer.last_request = now
        figures.keyframe_requests += 1
        self._request_keyframe(peer.name, peer.next_seq or peer.snapshot.seq)

    def _request_keyframe(self, name: str, seq: int) -> None:
        """Ask ``name`` for a keyframe after its frame ``seq`` (any thread)."""
        request = bytes(KeyframeRequest(min(seq, 2**32 - 1)))
        metadata = self.key.metadata(self.name, CONTROL + name.encode())
        sealed = self.sealer.seal(request, metadata)
        self.publish(subjects.control(self.key.room, name, self.name), sealed)

    def _control(self, sender: str, data: bytes) -> None:
        try:
            kid = Header.parse(data)[0].kid
            if not self.opener.knows(kid):
                if not kid_is_of(kid, sender):
                    raise SFrameError(f"KID {kid:#x} is not {sender}'s")
                self.opener.add_key(kid, self.key.base_key(sender, kid))
            metadata = self.key.metadata(sender, CONTROL + self.name.encode())
            packet = decode(self.opener.open(data, metadata))
        except (SFrameError, PacketError) as exc:
            self._rejected(sender, exc)
            return
        if isinstance(packet, KeyframeRequest) and self.on_keyframe_request is not None:
            logger.info("%s asks for a keyframe", sender)
            self.on_keyframe_request(packet)

    def _rejected(self, sender: str, exc: Exception) -> None:
        self.rejected[sender] += 1
        logger.debug("from %s: %s", sender, exc)
        if sender in self.told:
            return
        if isinstance(exc, KeyUnavailable):
            self.told.add(sender)
            self.notify(str(exc))
        elif "authenticate" in str(exc):
            self.told.add(sender)
            self.notify(
                f"{sender}'s messages do not open with this room key: is --key the key of "
                f"room {self.key.room}? ({sender} stays hidden)"
            )

    def _drop(self, peer: Peer, why: str, play_out: bool = False) -> None:
        """``peer`` has left: its sound (played out first when ``play_out``) and recording
        are finished on a thread of their own, so the other peers' pictures do not wait."""
        self.peers.pop(peer.name, None)
        figures = self.figures[peer.name]
        figures.left = why
        figures.recorded_from = peer.first_seq
        peer.close()

        def finish() -> None:
            try:
                figures.add_sound(peer.finish(play_out))
            except Exception as exc:  # said by facewire room once all is closed
                logger.debug("finishing %s", peer.name, exc_info=True)
                self.finish_errors.append(exc)

        finishing = threading.Thread(target=finish, name=f"finish-{peer.name}", daemon=True)
        finishing.start()
        self.finishing.append(finishing)
        if self.gallery is not None:
            self.gallery.left(peer.name)
        self.notify(f"{peer.name} left ({why})")

    def close(self) -> None:
        """Drop who is left and wait until every recording is finished (what went wrong
        finishing one is in :attr:`finish_errors`); newcomers still being joined are not
        shown."""
        for joining in self.joining.values():
            try:
                joining.discard()
            except Exception:  # leaving anyway
                logger.debug("discarding %s", joining.name, exc_info=True)
        self.joining.clear()
        for peer in list(self.peers.values()):
            self._drop(peer, "this participant left")
        for finishing in self.finishing:
            finishing.join()

    def stats(self) -> dict[str, Any]:
        return {name: f.as_dict() for name, f in self.figures.items()}
