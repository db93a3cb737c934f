"""The receiving end of a call: join, rebuild every frame, record, measure.

:func:`run_receiver` is the receive loop. Besides the MP4 recording, every rendered picture
can be handed to a frame sink (a live view, say) with the report's figures so far, and the
loop can be asked to stop (a signal handler) at any time: the recording is then closed
properly and the report returned as usual.
"""

from __future__ import annotations

import importlib
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from facewire.protocol.channels import ChainBroken, FrameValues
from facewire.protocol.clock import now_us
from facewire.protocol.constants import CALL, DRAFT, REFINED, SCENE, SNAPSHOT_MS
from facewire.protocol.packets import AudioFrame, Bye, DeltaFrame, KeyFrame, PacketError, Snapshot
from facewire.protocol.pauses import settle
from facewire.protocol.transport import ReceiverEndpoint, RejoinNeeded, TransportError
from facewire.receiver.audio import CallSound
from facewire.receiver.decoder import FaceDecoder, SnapshotError, new_scene_news
from facewire.receiver.interpolation import Painter
from facewire.receiver.lateness import LateFrames
from facewire.receiver.playout import Playout, PlayoutSettings, Record, Show, Step, make_playout
from facewire.receiver.recording import BackgroundRecorder
from facewire.receiver.smoothness import display_figures

logger = logging.getLogger(__name__)

#: The most frames one gap may fill with the held picture (beyond it the recording jumps:
#: a hostile or broken sequence number must not write millions of frames).
MAX_HOLD_FRAMES = 300
#: Keyframe requests while the chain is broken are repeated after this long, then twice as long
#: each time up to KEYFRAME_RETRY_MAX_S: each request brings a keyframe and every eye and
#: mouth patch again, and on a full 16 kbit/s link four a second kept it full (tbf dropping,
#: the chain breaking again) for 25 s.
KEYFRAME_RETRY_S = 0.25
KEYFRAME_RETRY_MAX_S = 2.0
#: While waiting for a session, how often a stop request is looked at.
STOP_CHECK_S = 0.5
#: A receive that blocked this long (µs) saw its packet come while it waited.
WAITED_US = 200
#: Time a stopped receiver gives its last message ("left") to reach the sender.
LINGER_S = 0.5
#: How long a receiver whose sender's packets name another session waits for that session's
#: snapshot before it takes the session as ended.
SCENE_FETCH_S = 10.0


@dataclass
class ReceiverReport:
    """What the receiving side measured over one call."""

    frames_out: int = 0
    frames_held: int = 0  # written again: no packet (nothing changed, or lost)
    frames_skipped: int = 0  # decoded but not rendered: a newer frame was already waiting
    keyframe_requests: int = 0
    chain_breaks: int = 0
    sessions: int = 0  # sessions joined (a restarted sender starts a new one)
    # New scenes of the call (the sender cut to another shot: a session that follows on), and
    # for each, when its first picture went on screen (µs, this end's clock: against the
    # sender's capture of the scene's first frame where both share one).
    scenes: int = 0
    scene_shown_us: list[int] = field(default_factory=list)
    # Runs of frames shown stale because packets were lost: (first seq, frames) per run.
    freezes: list[tuple[int, int]] = field(default_factory=list)
    # Per session: seconds from asking for its snapshot to its first rendered frame.
    first_frame_s: list[float] = field(default_factory=list)
    busy_s: float = 0.0  # own processing time: deform + render + record
    latency_ms: list[float] = field(default_factory=list)
    malformed: int = 0
    # Snapshots this receiver could not use (another rig, images that do not decode...), and
    # updates of another session or by another connection, ignored (docs/protocol.md 3.8).
    refused_snapshots: int = 0
    ignored_sessions: int = 0
    bytes_received: dict[str, int] = field(default_factory=dict)
    bytes_sent: dict[str, int] = field(default_factory=dict)
    ended_by: str = ""
    keyframe_interval: int = 0  # frames, the last session's (a freeze should not outlast it)
    # Playout: its settings, the delay the buffer aimed at (the last session's, µs), display
    # ticks passed over because the loop was busy, how long each frame shown as it is waited
    # in the buffer (ms), and every picture shown: (ready, depicted instant) µs.
    playout: str = ""
    display_fps: float = 0.0
    playout_delay_us: int = 0
    ticks_missed: int = 0
    buffer_ms: list[float] = field(default_factory=list)
    # Capture (the sender's stamp) to arrival of each frame decoded, ms: its spread is the
    # network's jitter; the values themselves mean something only where the ends share a clock.
    arrival_ms: list[float] = field(default_factory=list)
    shown: list[tuple[int, int]] = field(default_factory=list)
    audio: dict[str, Any] = field(default_factory=dict)  # receiver/audio.py, AudioReport
    # REM patches: received, applied (by region) and dropped (by reason), all sessions.
    rem: dict[str, Any] = field(default_factory=dict)
    # The second path (protocol/transport.py): frames that came late, copies dropped, copies
    # that came LATE_FRAME_MS or more after the first, and of those the frames it brought first.
    second_path: dict[str, int] = field(default_factory=dict)
    # The media path (protocol/media_path.py): datagrams and their bytes on the wire each way,
    # those dropped by why, updates that came by both paths.
    media: dict[str, Any] = field(default_factory=dict)
    refined: int = 0  # full snapshots taken after their draft

    def latency_each_second(self) -> list[float]:
        """The longest latency of the pictures shown in each second from the first one, ms
        (where a call was slow, not only how often: a join's first seconds, a burst)."""
        count = min(len(self.latency_ms), len(self.shown))  # appended together
        if count == 0:
            return []
        ready = np.asarray([r for r, _ in self.shown[:count]], np.int64)
        second = (ready - ready[0]) // 1_000_000
        most = np.zeros(int(second[-1]) + 1)
        np.maximum.at(most, second, np.asarray(self.latency_ms[:count]))
        return [round(float(v), 1) for v in most]

    def as_dict(self) -> dict:
        lat = np.asarray(self.latency_ms) if self.latency_ms else np.zeros(1)
        wait = np.asarray(self.buffer_ms) if self.buffer_ms else np.zeros(1)
        arrival = np.asarray(self.arrival_ms) if self.arrival_ms else np.zeros(1)
        return {
            "frames_out": self.frames_out,
            "frames_held": self.frames_held,
            "frames_skipped": self.frames_skipped,
            "keyframe_requests": self.keyframe_requests,
            "chain_breaks": self.chain_breaks,
            "sessions": self.sessions,
            "scenes": self.scenes,
            "scene_shown_us": list(self.scene_shown_us),
            "freezes": [list(f) for f in self.freezes],
            "first_frame_s": list(self.first_frame_s),
            "receiver_fps": self.frames_out / self.busy_s if self.busy_s > 0 else 0.0,
            "latency_ms": {
                "p50": float(np.percentile(lat, 50)),
                "p90": float(np.percentile(lat, 90)),
                "p99": float(np.percentile(lat, 99)),
                "max": float(lat.max()),
            },
            "latency_ms_each_second": self.latency_each_second(),
            "malformed": self.malformed,
            "refused_snapshots": self.refused_snapshots,
            "ignored_sessions": self.ignored_sessions,
            "bytes_received": dict(self.bytes_received),
            "bytes_sent": dict(self.bytes_sent),
            "ended_by": self.ended_by,
            "keyframe_interval": self.keyframe_interval,
            "audio": self.audio,
            "rem": dict(self.rem),
            "second_path": dict(self.second_path),
            "media": dict(self.media),
            "refined": self.refined,
            "playout": {
                "mode": self.playout,
                "display_fps": self.display_fps,
                "delay_ms": self.playout_delay_us / 1000.0,
                "arrival_ms": {
                    "min": float(arrival.min()),
                    **{f"p{q}": float(np.percentile(arrival, q)) for q in (50, 90, 95, 99)},
                },
                "buffer_ms": {
                    "p50": float(np.percentile(wait, 50)),
                    "p99": float(np.percentile(wait, 99)),
                },
                "ticks_missed": self.ticks_missed,
                "display": display_figures(
                    self.shown, 1e6 / self.display_fps if self.display_fps else 0.0
                ),
            },
        }


@dataclass(frozen=True)
class RenderedFrame:
    """A picture the receiver has just put on screen (held pictures are not passed again).

    seq : the sender's frame it shows, or (a picture between two frames) the one before it
    image : (h, w, 3) uint8 BGR at the session's size
    capture_us : the instant it shows on the sender's clock (its monotonic clock, µs): the
        frame's capture time, or a time between two frames' for a picture between them
    latency_ms : that instant to this rendered picture, meaningful where both ends share a
        clock
    """

    session_id: int
    seq: int
    image: np.ndarray
    capture_us: int
    latency_ms: float


#: Called with every rendered picture and the report so far (live figures). It runs on the
#: receive loop's thread: it must return quickly, and must not change the picture (the
#: recording may still be encoding it): hand it on, or copy it to draw on it.
FrameSink = Callable[[RenderedFrame, ReceiverReport], None]


def _never() -> bool:
    return False


def _quiet(message: str) -> None:
    logger.info("%s", message)


def run_receiver(
    host: str,
    pub_port: int,
    snapshot_port: int,
    output: str | None,
    join_timeout_s: float = 20.0,
    rejoin_timeout_s: float = 0.0,
    *,
    sink: FrameSink | None = None,
    stop: Callable[[], bool] = _never,
    notify: Callable[[str], None] = _quiet,
    playout: PlayoutSettings | None = None,
    sound: bool = True,
    record_from: int | None = None,
    **endpoint_options: Any,
) -> ReceiverReport:
    """Join the call at ``host`` and record the rebuilt frames to ``output`` (None: no file).

    ``endpoint_options`` go to :class:`~facewire.protocol.transport.ReceiverEndpoint`: the keys
    (``secret_key_file`` and ``server_key_file`` for CURVE, or ``plain=True``) and
    ``bind=True`` to bind on ``host`` for a sender that connects.

    Frames are played out as ``playout`` says (receiver/playout.py; default: a jitter buffer
    whose delay adapts to the network's jitter, pictures at the sender's frame rate): every
    picture put on screen is passed to ``sink``. Frame i of the recording rebuilds the
    sender's frame i: a frame with no packet (nothing changed, or the packet was lost) or one
    that came too late to be shown repeats the previous picture, so the recording stays
    aligned. After a gap the picture holds and a keyframe is requested until one arrives.
    The recording begins at the first session's snapshot frame (a late joiner's, where it
    joined), or with ``record_from`` at that frame of the sender's: a receiver there from the
    start of a file whose first face comes late shows the first picture until then.

    A session ends with the sender's Bye, when the sender is silent for PEER_TIMEOUT_S, or when
    it restarts (a new session on the same address). With ``rejoin_timeout_s`` > 0 the
    receiver then waits that long for the next session and records it on, scaled to the
    recording's size; otherwise the call ends. Either timeout may be ``math.inf``.

    ``stop()`` is looked at between frames and while waiting: once it is True the call ends
    (``ended_by`` "stopped") and the recording is closed with its index. ``notify`` gets one
    line per event a person watching wants to know (a session began or ended). Raises
    TransportError when no sender came within ``join_timeout_s``.
    """
    report = ReceiverReport()
    settings = playout or PlayoutSettings()
    report.playout = settings.describe()
    with ReceiverEndpoint(host, pub_port, snapshot_port, **endpoint_options) as endpoint:
        ports = endpoint.ports
        how = "on" if endpoint_options.get("bind") else "at"
        notify(f"waiting for a sender {how} tcp://{host}:{ports[0]} (and :{ports[1]})")
        started = time.monotonic()
        _import_renderer_meanwhile()
        joined = _join(endpoint, join_timeout_s, stop, report, notify)
        if joined is None:
            report.ended_by = "stopped"
            return report
        snapshot, decoder = joined
        recorder = (
            BackgroundRecorder(output, snapshot.width, snapshot.height, snapshot.fps)
            if output is not None
            else None
        )
        first = snapshot.seq if record_from is None else min(record_from, snapshot.seq)
        audio = CallSound(report.shown, first, snapshot.fps, notify) if sound else None
        try:
            scene: _Ended | None = None  # the scene before, when this session follows on it
            before = report.frames_out
            # The call's first session, as its new scenes' snapshots name it.
            call: str | int | float = snapshot.session_id
            while joined is not None:
                snapshot, decoder = joined
                if scene is None:
                    call = snapshot.meta.get(CALL, snapshot.session_id)
                    report.sessions += 1
                    before = report.frames_out
                    notify(
                        f"session {snapshot.session_id}: {snapshot.width}x{snapshot.height} at "
                        f"{snapshot.fps:g} fps"
                    )
                else:
                    report.scenes += 1
                    notify(new_scene_news(snapshot))
                report.keyframe_interval = snapshot.keyframe_interval
                out = _Output(recorder, sink, snapshot.session_id, report)
                begins = record_from is not None and scene is None and report.sessions == 1
                ended = _receive_session(
                    endpoint, decoder, snapshot, out, report, started, stop, settings, audio, scene,
                    first if begins else None,
                )  # fmt: skip
                report.ended_by = ended.reason
                frames = report.frames_out - before
                joined, scene = None, None
                if report.ended_by == "stopped":
                    break
                if ended.session is not None:
                    # The sender's packets name another session: a new scene of this call, or
                    # a restarted sender. Its snapshot says which.
                    started = time.monotonic()
                    joined = _next_session(endpoint, stop, report, notify)
                    if joined is not None and joined[0].meta.get(CALL) == call:
                        scene = ended
                        continue
                waiting = rejoin_timeout_s > 0
                notify(
                    f"session ended ({report.ended_by}) after {frames} frames"
                    + ("; waiting for a new session" if waiting else "")
                )
                if not waiting:
                    joined = None
                elif joined is None:
                    started = time.monotonic()
                    try:
                        joined = _join(endpoint, rejoin_timeout_s, stop, report, notify)
                    except TransportError as exc:
                        logger.info("no new session: %s", exc)
                        notify(f"no new session within {rejoin_timeout_s:g} s")
                    if joined is None and stop():
                        report.ended_by = "stopped"
        finally:
            if recorder is not None:
                recorder.close()  # writes the MP4's index, whatever ended the call
            if audio is not None:
                report.audio = audio.finish(output)
        if report.ended_by == "stopped":
            endpoint.send_stats({"left": 1.0})  # the sender may wait for another receiver
        report.malformed += endpoint.stats.malformed
        report.ignored_sessions = endpoint.stats.ignored_sessions
        stats = endpoint.stats
        report.second_path = {
            "late_frames": stats.late_frames,
            "copies": stats.copies,
            "late_copies": stats.late_copies,
            "saved": stats.saved,
        }
        report.bytes_received = dict(endpoint.bytes_received)
        report.bytes_sent = dict(endpoint.bytes_sent)
        report.media = endpoint.media_figures()
        endpoint.close(linger_s=LINGER_S)
    return report


def _import_renderer_meanwhile() -> None:
    """Import the renderer (pyrender, PyOpenGL: about 0.5 s) while the snapshot is on its way,
    not after it came: on a thin link the first picture is that much sooner."""
    threading.Thread(
        target=importlib.import_module, args=("facewire.receiver.render",), name="import-renderer",
        daemon=True,
    ).start()  # fmt: skip


def _join(
    endpoint: ReceiverEndpoint,
    timeout_s: float,
    stop: Callable[[], bool],
    report: ReceiverReport,
    notify: Callable[[str], None] = _quiet,
) -> tuple[Snapshot, FaceDecoder] | None:
    """The next session this receiver can draw: its snapshot and decoder. A snapshot it cannot
    use (another rig, images that do not decode, another channel table) is refused, counted,
    and another asked for (a stranger may have answered on a bound DEALER); None once
    ``stop()``; TransportError after ``timeout_s``, naming the last refusal. A handshake that
    fails (a key that does not match) is told to ``notify`` once, as it happens."""
    deadline = time.monotonic() + timeout_s
    refused = ""
    while True:
        try:
            snapshot = _wait_for_session(endpoint, deadline, timeout_s, stop, notify)
        except TransportError as exc:
            raise TransportError(f"{exc}{refused}") from None
        if snapshot is None:
            return None
        try:
            return snapshot, FaceDecoder(snapshot)
        except SnapshotError as exc:
            report.refused_snapshots += 1
            refused = f" (a snapshot came, but was refused: {exc})"
            endpoint.refusals.refuse(f"refused session {snapshot.session_id}'s snapshot: {exc}")


def _next_session(
    endpoint: ReceiverEndpoint,
    stop: Callable[[], bool],
    report: ReceiverReport,
    notify: Callable[[str], None],
) -> tuple[Snapshot, FaceDecoder] | None:
    """The session the sender's packets now name: its snapshot and decoder (None: it did not
    come within SCENE_FETCH_S, or ``stop()``)."""
    try:
        return _join(endpoint, SCENE_FETCH_S, stop, report, notify)
    except TransportError as exc:
        logger.info("the sender's new session did not come: %s", exc)
        return None


def _wait_for_session(
    endpoint: ReceiverEndpoint,
    deadline: float,
    timeout_s: float,
    stop: Callable[[], bool],
    notify: Callable[[str], None] = _quiet,
) -> Snapshot | None:
    """The next session's snapshot; None once ``stop()``; TransportError at ``deadline``
    (``time.monotonic()``; ``timeout_s`` is how long the caller waits in all, for the message).

    Without a way to stop (the default) it is one handshake attempt; otherwise attempts of at
    most STOP_CHECK_S, so a stop request is seen soon.
    """
    if stop is _never and math.isfinite(deadline):
        return endpoint.fetch_snapshot(timeout_ms=_ms(max(0.001, deadline - time.monotonic())))
    told: str | None = None
    while not stop():
        attempt = _ms(min(STOP_CHECK_S, max(0.001, deadline - time.monotonic())))
        try:
            return endpoint.fetch_snapshot(timeout_ms=attempt)
        except TransportError as exc:
            failed = endpoint.handshake_error
            if failed is not None and failed != told:
                notify(f"cannot join: {failed}")
            told = failed
            if time.monotonic() >= deadline:
                reason = str(exc).replace(f" within {attempt} ms", "")
                raise TransportError(f"no sender within {timeout_s:g} s: {reason}") from None
    return None


class _Output:
    """Where one session's frames go: the recording (if any) and the sink; counts them."""

    def __init__(
        self,
        recorder: BackgroundRecorder | None,
        sink: FrameSink | None,
        session_id: int,
        report: ReceiverReport,
    ) -> None:
        self.recorder = recorder
        self.sink = sink
        self.session_id = session_id
        self.report = report
        self.size = recorder.size if recorder is not None else None

    def fit(self, image: np.ndarray) -> np.ndarray:
        """``image`` at the recording's (width, height): a later session may have another."""
        return image if self.size is None else _fit(image, self.size)

    def write(self, image: np.ndarray) -> None:
        """Frame ``frames_out`` of the recording."""
        if self.recorder is not None:
            self.recorder.write(image)
        self.report.frames_out += 1

    def show(self, image: np.ndarray, seq: int, media_us: int, latency_ms: float) -> None:
        if self.sink is not None:
            self.sink(RenderedFrame(self.session_id, seq, image, media_us, latency_ms), self.report)


@dataclass
class _Ended:
    """Why a session's loop ended, and where its recording stands."""

    reason: str
    session: int | None = None  # the session the sender's packets went on with
    last: np.ndarray | None = None  # the recording's last picture
    next_seq: int = 0  # the recording's next frame


def _receive_session(
    endpoint: ReceiverEndpoint,
    decoder: FaceDecoder,
    snapshot: Snapshot,
    out: _Output,
    report: ReceiverReport,
    started: float,
    stop: Callable[[], bool],
    settings: PlayoutSettings,
    audio: CallSound | None = None,
    scene: _Ended | None = None,
    record_from: int | None = None,
) -> _Ended:
    """Rebuild, show and record one session's frames; returns why it ended.

    ``scene``: the end of the session this one follows on (the sender cut to a new scene): its
    last picture stays on screen, and in the recording, until this one's first.
    ``record_from``: the sender's frame the recording begins at (run_receiver's).
    """
    try:
        playout = make_playout(settings, snapshot.fps)
        report.display_fps = settings.display_fps or snapshot.fps
        player = _Player(Painter(decoder), out, report, snapshot, started, scene, record_from)
        lateness = LateFrames()
        settle()  # before the frames: no pause of the garbage collector among them
        # Tell the sender we can keep up from now on (building the decoder takes ~0.5 s), and
        # ask for the keyframe that starts our chain. A new scene's receiver is no new one.
        joined = SCENE if scene is not None else "ready"
        endpoint.send_stats({joined: 1.0, SNAPSHOT_MS: endpoint.snapshot_ms})
        if scene is not None:
            player.scene_still(decoder.reference)
        endpoint.request_keyframe(snapshot.seq)
        last_request = time.monotonic()
        retry_s = KEYFRAME_RETRY_S
        broken = False  # the chain broke since the last frame decoded
        needed = snapshot.seq  # the first frame not decoded yet
        while True:
            if stop():
                return player.ended("stopped", broken=broken)
            try:
                waited_from = now_us()
                packet = endpoint.recv(timeout_ms=_ms(playout.wait_us(waited_from) / 1e6))
                received = endpoint.arrival_us
                # A packet that came while the loop waited is stamped when it came; one already
                # queued (it came while a picture was drawn) only when the loop got back to it,
                # which says little about the network: it does not count towards the spread.
                # Each packet has its own datagram's time: the frames of one datagram share it
                # (the playout draws them at their own pace), and a frame read while this loop
                # took the ones before it is not stamped before its capture.
                timed = received - waited_from >= WAITED_US
                first = received
                while packet is not None and not isinstance(packet, Bye):
                    if audio is not None and isinstance(packet, AudioFrame):
                        audio.push(packet, now_us())
                    if decoder.offer(packet):  # a REM patch, drawn with its frame
                        pass
                    elif isinstance(packet, Snapshot):  # a sharper one after its draft
                        if not decoder.refine(packet):
                            pass
                        elif packet.meta.get(DRAFT):  # the full one is still to come
                            logger.info("a sharper draft of the snapshot came")
                        else:
                            report.refined += 1
                            endpoint.send_stats({REFINED: 1.0})
                            logger.info("the snapshot's full images came: drawn from now on")
                    elif isinstance(packet, (KeyFrame, DeltaFrame)):
                        values = _decode(decoder, packet, report)
                        if values is None:
                            broken = True
                        else:
                            playout.push(values, received, broken, timed)
                            if audio is not None:
                                audio.frame(values.seq, values.capture_us, received)
                            report.arrival_ms.append((received - values.capture_us) / 1000.0)
                            if timed and lateness.late(received, values.capture_us):
                                endpoint.note_late_frame()
                            broken = False
                            needed = max(needed, values.seq + 1)
                    packet = endpoint.recv(timeout_ms=0)
                    received = endpoint.arrival_us
                    timed = timed and received == first
            except RejoinNeeded as exc:
                return player.ended(f"sender restarted ({exc})", exc.session)
            if decoder.channels.intact:
                retry_s = KEYFRAME_RETRY_S
            elif time.monotonic() - last_request > retry_s:
                endpoint.request_keyframe(needed)
                report.keyframe_requests += 1
                last_request = time.monotonic()
                retry_s = min(2 * retry_s, KEYFRAME_RETRY_MAX_S)
            player.run(playout.poll(now_us()), endpoint)
            _note_playout(report, playout)
            if isinstance(packet, Bye):
                # Play out what the buffer still holds, at its pace, then end.
                while playout.pending and not stop():
                    time.sleep(min(playout.wait_us(now_us()) / 1e6, STOP_CHECK_S))
                    player.run(playout.poll(now_us()), endpoint)
                _note_playout(report, playout)
                report.frames_held += _hold(out, player.last, packet.seq - player.next_seq)
                return player.ended("bye", broken=broken, end_seq=packet.seq)
            if packet is None and not playout.pending and not endpoint.peer_alive:
                return player.ended("peer lost", broken=broken)
    finally:
        for key, value in decoder.rem_counts().items():
            report.rem[key] = _added(report.rem.get(key), value)
        decoder.close()


def _added(a: Any, b: Any) -> Any:
    """Counts of two sessions added (numbers, or dicts of numbers)."""
    if a is None:
        return b
    if isinstance(b, dict):
        return {k: a.get(k, 0) + b.get(k, 0) for k in {*a, *b}}
    return a + b


def _note_playout(report: ReceiverReport, playout: Playout) -> None:
    report.playout_delay_us = playout.delay_us
    report.ticks_missed = getattr(playout, "ticks_missed", 0)


class _Player:
    """Carries out the playout's steps: draws, records, shows, and counts."""

    def __init__(
        self,
        painter: Painter,
        out: _Output,
        report: ReceiverReport,
        snapshot: Snapshot,
        started: float,
        scene: _Ended | None = None,
        record_from: int | None = None,
    ) -> None:
        self.painter = painter
        self.out = out
        self.report = report
        self.snapshot = snapshot
        self.started = started
        # The recording's next frame; from ``record_from`` on, every frame before the first
        # picture shows it, however many (else at most a second's: a late joiner's start).
        self.next_seq = snapshot.seq if record_from is None else record_from
        self.fill_from_start = record_from is not None
        self.last: np.ndarray | None = None  # the recording's last picture
        self.stale_from: int | None = None  # first frame of a freeze (packets were lost)
        # A new scene: the scene before stays until its first picture (whose time is noted).
        self.new_scene = scene is not None
        if scene is not None:
            self.last, self.next_seq = scene.last, scene.next_seq

    def scene_still(self, values: FrameValues) -> None:
        """A new scene's first frame (its snapshot frame, drawn from its ``values``) on screen
        and in the recording at once: what the camera showed at the cut, until its frames
        come."""
        start = time.perf_counter()
        self.record(Record(values.seq, values))
        assert self.last is not None
        ready = now_us()
        self.report.scene_shown_us.append(ready)
        self.new_scene = False
        self.out.show(self.last, values.seq, ready, 0.0)
        self.report.busy_s += time.perf_counter() - start

    def ended(
        self,
        reason: str,
        session: int | None = None,
        *,
        broken: bool = False,
        end_seq: int | None = None,
    ) -> _Ended:
        """The session is over. ``broken``: its chain was broken at the end (the picture froze
        and no packet came to end the freeze); ``end_seq``: the frame after its last (default:
        after the last one recorded)."""
        if broken and self.stale_from is None and self.last is not None:
            self.stale_from = self.next_seq
        end = self.next_seq if end_seq is None else end_seq
        if self.stale_from is not None and end > self.stale_from:
            # Frozen until the end: a freeze all the same, which the report must not hide.
            self.report.freezes.append((self.stale_from, end - self.stale_from))
            self.stale_from = None
        return _Ended(reason, session, self.last, self.next_seq)

    def run(self, steps: list[Step], endpoint: ReceiverEndpoint) -> None:
        for step in steps:
            start = time.perf_counter()
            if isinstance(step, Record):
                self.record(step)
            else:
                self.show(step, endpoint)
            self.report.busy_s += time.perf_counter() - start

    def record(self, step: Record) -> None:
        report, out = self.report, self.out
        if step.after_gap and self.stale_from is None and self.last is not None:
            self.stale_from = self.next_seq
        if step.values is None:  # too late to be shown
            report.frames_skipped += 1
            if self.last is not None:  # else the first picture fills it (below)
                report.frames_held += _hold(out, self.last, step.seq + 1 - self.next_seq)
                self.next_seq = max(self.next_seq, step.seq + 1)
            return
        report.frames_held += _hold(out, self.last, step.seq - self.next_seq)
        if self.stale_from is not None:
            report.freezes.append((self.stale_from, step.seq - self.stale_from))
            self.stale_from = None
        picture = out.fit(self.painter.exact(step.values))
        if self.last is None:
            report.first_frame_s.append(time.monotonic() - self.started)
            # Frames of the session's first second that came before its first decodable
            # packet show that first picture, so the recording stays aligned; a late
            # joiner's recording starts where it joined.
            early = step.seq - self.next_seq
            if early <= self.snapshot.fps or self.fill_from_start:
                report.frames_held += _hold(out, picture, early)
        out.write(picture)
        self.last = picture
        self.next_seq = step.seq + 1

    def show(self, step: Show, endpoint: ReceiverEndpoint) -> None:
        if step.b is None:
            picture = self.painter.exact(step.a)
        else:
            picture = self.painter.between(step.a, step.b, step.t)
        picture = self.out.fit(picture)
        ready = now_us()
        latency_ms = (ready - step.media_us) / 1000.0
        report = self.report
        if self.new_scene:
            report.scene_shown_us.append(ready)
            self.new_scene = False
        report.latency_ms.append(latency_ms)
        report.shown.append((ready, step.media_us))
        if step.arrival_us is not None:
            report.buffer_ms.append((ready - step.arrival_us) / 1000.0)
        report.bytes_received = dict(endpoint.bytes_received)
        self.out.show(picture, step.a.seq, step.media_us, latency_ms)


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


def _hold(out: _Output, last: np.ndarray | None, count: int) -> int:
    """Write the previous picture for ``count`` frames that had no packet (at most
    MAX_HOLD_FRAMES: a longer gap is a jump, not a still picture)."""
    if last is None or count <= 0:
        return 0
    if count > MAX_HOLD_FRAMES:
        logger.warning("gap of %d frames: holding only %d", count, MAX_HOLD_FRAMES)
        count = MAX_HOLD_FRAMES
    for _ in range(count):
        out.write(last)
    return count
