"""The sending end of a call: encode every frame, publish it, answer the back channel."""

from __future__ import annotations

import dataclasses
import itertools
import logging
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import cv2

from facewire.protocol.clock import now_us
from facewire.protocol.constants import SCENE
from facewire.protocol.packets import (
    Bye,
    DeltaFrame,
    KeyFrame,
    KeyframeRequest,
    Packet,
    ReceiverStats,
    Refresh,
    RemPatch,
    Snapshot,
)
from facewire.protocol.transport import SenderEndpoint, TransportError
from facewire.sender.capture import CapturedFrame, CaptureError
from facewire.sender.encoder import FaceEncoder
from facewire.sender.lift import MarkerFaceTracker
from facewire.sender.markers import NO_MARKERS
from facewire.sender.refresh import REFRESH_KBPS
from facewire.sender.rem import BUDGET_KBPS as EYES_KBPS
from facewire.sender.rem import MOUTH_BUDGET_KBPS
from facewire.sender.scene_cut import FACE_LOST_S
from facewire.sender.snapshot_draft import draft, sharper

logger = logging.getLogger(__name__)

#: Seconds of input looked through for a first face with the marker tracker (a title card, an
#: empty chair before it; with landmarks, the scene alone is sent after FACE_LOST_S), of
#: which the last FACE_SEARCH_KEEP frames are kept to be sent (a 1280x720 frame is 2.8 MB). A
#: recording that begins at the input's first frame shows the first picture for those before.
FACE_SEARCH_S = 10.0
FACE_SEARCH_KEEP = 60
#: At the input's end, a receiver still joining the last new scene is waited for this long.
SCENE_JOIN_WAIT_S = 3.0

FramePacket = KeyFrame | DeltaFrame
#: How often the pictures' budget follows the link's (frames).
BUDGET_EVERY_FRAMES = 15
#: The pictures' budget on a wide link, payload: the eyes', the mouth's inside's and the
#: refreshes' together.
PICTURES_KBPS = EYES_KBPS + MOUTH_BUDGET_KBPS + REFRESH_KBPS
#: What the sender publishes per frame: its REM patches and refreshes, then its frame packet.
UpdatePacket = KeyFrame | DeltaFrame | RemPatch | Refresh


@dataclass
class SenderReport:
    """What the sending side measured over one call."""

    frames_in: int = 0
    packets: int = 0  # frame packets handed to the link (no packet: nothing changed)
    patches: int = 0  # REM patches handed to the link
    refreshes: int = 0  # refreshes of what the model misses (sender/refresh.py) handed to it
    keyframe_requests: int = 0
    # Sessions started at a cut to another scene, and each one's first frame: its number and
    # its capture time (µs, this end's clock).
    scenes: int = 0
    scenes_joined: int = 0  # of them, how many a receiver said it joined ("scene")
    scene_frames: list[int] = field(default_factory=list)
    scene_capture_us: list[int] = field(default_factory=list)
    busy_s: float = 0.0  # own processing time: track + encode + publish
    receiver_stats: dict[str, float] = field(default_factory=dict)  # the latest of each name
    stopped: bool = False  # ended by a stop request, not by the end of the input

    @property
    def fps(self) -> float:
        return self.frames_in / self.busy_s if self.busy_s > 0 else 0.0


def _never() -> bool:
    return False


def run_sender(
    endpoint: SenderEndpoint,
    encoder: FaceEncoder,
    frames: Iterable[CapturedFrame],
    publish: Callable[[UpdatePacket], None] | None = None,
    stop: Callable[[], bool] = _never,
    on_stats: Callable[[dict[str, float]], None] | None = None,
    read_to: Callable[[], int] | None = None,
) -> SenderReport:
    """Encode and publish every frame of ``frames``, then say Bye.

    ``encoder`` has started (its snapshot is set on ``endpoint``). Between frames the back
    channel is read: a KeyframeRequest makes the next packet a keyframe, ReceiverStats are kept
    in the report. Heartbeats go out when nothing was published for a second. A frame's REM
    patches go out just before its frame packet. ``publish`` replaces ``endpoint.publish``
    for both (a test's lossy link). Once ``stop()`` is
    True (looked at before each frame) the call ends the same way, with a Bye. ``on_stats``
    sees each ReceiverStats as it comes (a receiver says "ready" when it joins, "left" when
    it goes). ``read_to`` gives the number of the input's frame after the last one read: the
    Bye names it, so frames left out at the end (a busy machine) are held there too.

    A frame of another scene (``FaceEncoder.scene_changed``: a cut) starts a session from it
    (:class:`_SceneStart`), whose snapshot (and its draft) the endpoint serves from then on;
    the frames that come while it is built are not sent (the receiver keeps its picture).
    """
    report = SenderReport()
    next_seq = 0
    scene: _SceneStart | None = None
    waiting: list[Packet] = []  # the back channel's packets while the encoder was busy
    for frame in frames:
        if stop():
            report.stopped = True
            break
        next_seq = frame.index + 1
        if scene is not None:
            scene.serve(endpoint, report)
        if scene is not None and not scene.done():
            # The encoder is busy: nothing to send. The endpoint answers snapshot requests;
            # what is for the encoder waits.
            waiting.extend(endpoint.poll(0))
            _skip(endpoint, report)
            continue
        scene = None
        _read_back_channel(endpoint, encoder, report, on_stats, waiting)
        waiting = []
        start = time.perf_counter()
        if encoder.scene_changed(frame):
            scene = _SceneStart(encoder, frame)
            report.busy_s += time.perf_counter() - start
            _skip(endpoint, report)
            continue
        packet = encoder.encode(frame)
        for patch in encoder.take_patches():
            if publish is None:
                endpoint.publish(patch)
            else:
                publish(patch)
            if isinstance(patch, Refresh):
                report.refreshes += 1
            else:
                report.patches += 1
        if packet is not None:  # None: nothing visible changed since the last packet
            if publish is None:  # with the frame number for heartbeats (a delta has none)
                endpoint.publish(packet, seq=frame.index)
            else:
                publish(packet)
            report.packets += 1
        report.busy_s += time.perf_counter() - start
        report.frames_in += 1
        endpoint.heartbeat_if_idle()
        endpoint.end_frame()
        if report.frames_in % BUDGET_EVERY_FRAMES == 0:
            share_pictures_budget(encoder, endpoint.patch_budget_bps() / 1000.0)
    if scene is not None:
        scene.done(wait=True)  # the encoder is the caller's again
        scene.serve(endpoint, report)  # its first frame stands for the frames skipped
    _until_scene_joined(endpoint, encoder, report, on_stats)
    if read_to is not None:
        next_seq = max(next_seq, read_to())
    endpoint.publish(Bye(seq=next_seq))
    _read_back_channel(endpoint, encoder, report, on_stats)
    return report


def share_pictures_budget(encoder: FaceEncoder, left_kbps: float) -> None:
    """The pictures take what the link's budget leaves (``left_kbps``), never more than their
    own: the eyes, the mouth's inside and the refreshes each the share of it they have of
    PICTURES_KBPS. (Once only the eyes followed the link: the mouth's inside and the
    refreshes, 3 kbit/s, came on top of what a thin link had left.)"""
    scale = min(1.0, max(0.0, left_kbps) / PICTURES_KBPS)
    if encoder.rem is not None:
        encoder.rem.set_budget(EYES_KBPS * scale)
    if encoder.refresh is not None:
        encoder.refresh.set_budget(REFRESH_KBPS * scale)


def _until_scene_joined(
    endpoint: SenderEndpoint,
    encoder: FaceEncoder,
    report: SenderReport,
    on_stats: Callable[[dict[str, float]], None] | None,
) -> None:
    """Before the Bye: where the input ended just after a new scene that a receiver of this
    call is still joining (it fetches the new snapshot: a draft waits for its datagrams' path
    up to a second), answer it for up to SCENE_JOIN_WAIT_S. A Bye sent meanwhile is not its
    session's: it waited for the new snapshot until its join timeout, and the frames after
    the cut were lost (a file that cut to a face in its last half second)."""
    if report.stopped or report.scenes_joined >= report.scenes or not endpoint.snapshots_served:
        return  # asked to stop, no scene since the last join, or none asks (a room's peers)
    deadline = time.monotonic() + SCENE_JOIN_WAIT_S
    while report.scenes_joined < report.scenes and time.monotonic() < deadline:
        endpoint.end_frame()  # what is bundled (the new session's Heartbeat) goes
        _read_back_channel(endpoint, encoder, report, on_stats, endpoint.poll(20))
        endpoint.heartbeat_if_idle()


class _SceneStart:
    """A new scene's session, started from ``frame`` on a thread of its own: the pseudo-inverse
    of its wires takes 50 ms on a quiet machine and seconds when the other core is busy (numpy
    leaves the GIL), long enough for a receiver to take the sender for gone. Meanwhile the
    call's loop leaves the encoder alone (the back channel's requests wait for it), keeps the
    link alive, and serves the snapshot as soon as it is made, before the fit is ready. Its
    smaller versions for a thin link are made here too (0.1-0.25 s at 640x480 and 1280x720)."""

    def __init__(self, encoder: FaceEncoder, frame: CapturedFrame) -> None:
        self.frame = frame
        #: The new session's snapshot once made (before the encoder's fit is ready), with its
        #: draft and the sharper versions that follow it (sender/snapshot_draft.py).
        self.snapshot: Snapshot | None = None
        self.draft: Snapshot | None = None
        self.sharper: list[Snapshot] = []
        self.served = False
        self._thread = threading.Thread(
            target=self._run, args=(encoder,), name="scene start", daemon=True
        )
        self._thread.start()

    def _run(self, encoder: FaceEncoder) -> None:
        snapshot = encoder.start_scene(self.frame, fit_now=False)
        if snapshot is not None:
            self.draft, self.sharper = draft(snapshot), sharper(snapshot)
        self.snapshot = snapshot  # last: the call's loop serves it with its versions
        if snapshot is not None:
            encoder.prepare_fit()

    def serve(self, endpoint: SenderEndpoint, report: SenderReport) -> None:
        """Serve the snapshot once it is made, and say so at once: the receiver shows the new
        scene's first frame while the encoder readies its fit."""
        if self.snapshot is None or self.served:
            return
        endpoint.set_snapshot(self.snapshot, self.draft, self.sharper)
        endpoint.heartbeat()
        self.served = True
        report.scenes += 1
        report.scene_frames.append(self.frame.index)
        report.scene_capture_us.append(self.frame.capture_us)

    def done(self, wait: bool = False) -> bool:
        if wait:
            self._thread.join()
        return not self._thread.is_alive()


def _skip(endpoint: SenderEndpoint, report: SenderReport) -> None:
    """A frame not sent: the link is kept alive."""
    report.frames_in += 1
    endpoint.heartbeat_if_idle()
    endpoint.end_frame()


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


def face_search(fps: float) -> int:
    """Frames of input at ``fps`` looked through for a first face (FACE_SEARCH_S)."""
    return max(1, round(FACE_SEARCH_S * fps))


def start_session(
    encoder: FaceEncoder,
    frames: Iterator[CapturedFrame],
    fps: float,
    name: str,
    seq: int | None = None,
) -> tuple[Snapshot, list[CapturedFrame]]:
    """Start ``encoder`` on the first frame that shows a face; with the landmark tracker, on
    the scene alone (``FaceEncoder.start_without_face``: no one in front of the camera yet)
    where none has shown one for FACE_LOST_S. Its session of the face begins when a face
    comes (``run_sender``).

    Returns the snapshot, valid from frame ``seq`` (default: the first frame kept), and the
    last FACE_SEARCH_KEEP frames read (the snapshot frame last): they still have to be sent.
    Raises CaptureError (one line, naming the source ``name``) when the input ends before,
    or with the marker tracker none of FACE_SEARCH_S of input shows a face, or the markers
    on it.
    """
    kept: deque[CapturedFrame] = deque(maxlen=FACE_SEARCH_KEEP)
    read = 0
    waits = round(FACE_LOST_S * fps)
    for frame in itertools.islice(frames, face_search(fps)):
        kept.append(frame)
        read += 1
        first = kept[0].index if seq is None else seq
        snapshot = encoder.start(frame, seq=first)
        if snapshot is None and encoder.scenes_without_face and read >= waits:
            logger.info("no face in the first %d frames: the scene alone until one comes", read)
            snapshot = encoder.start_without_face(frame, seq=first)
        if snapshot is not None:
            return snapshot, list(kept)
    if isinstance(encoder.tracker, MarkerFaceTracker) and encoder.tracker.state == NO_MARKERS:
        raise CaptureError(
            f"a face but no markers on it in the first {read} frames of {name} "
            "(--tracker markers: see the README for where they go)"
        )
    raise CaptureError(f"no face found in the first {read} frames of {name}")


def restamped(frames: list[CapturedFrame]) -> list[CapturedFrame]:
    """Frames read before the call began, counted as captured now (else their wait for the
    receiver would show as latency)."""
    now = now_us()
    return [dataclasses.replace(f, capture_us=now) for f in frames]


def capped_size(width: int, height: int, max_width: int, max_height: int) -> tuple[int, int]:
    """(width, height) scaled down, aspect kept, to fit ``max_width`` x ``max_height`` turned
    the way the input is (a phone held upright, 720x1280, fits 1280x720 as it is); even sides
    (video codecs want them); unchanged when it already fits."""
    long, short = max(max_width, max_height), min(max_width, max_height)
    max_width, max_height = (long, short) if width >= height else (short, long)
    scale = min(1.0, max_width / width, max_height / height)
    if scale >= 1.0:
        return width, height
    return max(2, round(width * scale / 2) * 2), max(2, round(height * scale / 2) * 2)


def scaled(frames: Iterable[CapturedFrame], size: tuple[int, int]) -> Iterator[CapturedFrame]:
    """``frames`` resized to ``size`` (width, height) where they differ: a call of a large
    input runs at a size the receiver can render in real time."""
    for frame in frames:
        if frame.image.shape[1::-1] != size:
            image = cv2.resize(frame.image, size, interpolation=cv2.INTER_AREA)
            frame = dataclasses.replace(frame, image=image)
        yield frame


def _read_back_channel(
    endpoint: SenderEndpoint,
    encoder: FaceEncoder,
    report: SenderReport,
    on_stats: Callable[[dict[str, float]], None] | None,
    earlier: Iterable[Packet] = (),
) -> None:
    """Take the back channel's packets (``earlier``: those read while the encoder was busy)."""
    for packet in itertools.chain(earlier, endpoint.poll(0)):
        if isinstance(packet, KeyframeRequest):
            logger.debug("keyframe requested after seq %d", packet.seq)
            encoder.request_keyframe()
            report.keyframe_requests += 1
        elif isinstance(packet, ReceiverStats):
            if packet.values.get(SCENE):
                report.scenes_joined = report.scenes
            report.receiver_stats.update(packet.values)
            if on_stats is not None:
                on_stats(dict(packet.values))
