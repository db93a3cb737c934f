"""Playout in a real call: real sockets on loopback, the receiver in its own process with real
rendering and a frame sink, the bundled clip sent at its frame rate.

Jitter is a link that holds the sender's packets back for 0 to 3 frame intervals, in order
(as TCP delivers: a late packet holds up the ones behind it), so they arrive in bursts. Loss
is tests/call_helpers.py's lossy link. Figures (how even the screen is, latency) are in
benchmarks/bench_playout.py; here: what is shown, in which order, never before it is due,
never guessed across a gap, and the recording frame by frame.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from call_helpers import (
    CTX,
    HOST,
    JOIN_TIMEOUT_S,
    Keys,
    LossyLink,
    mean_abs_diff,
    read_video,
    reference_frames,
    start_sender,
)
from test_recovery import face_box

from facewire.protocol.packets import DeltaFrame, KeyFrame, decode
from facewire.protocol.transport import SenderEndpoint
from facewire.sender.session import run_sender, wait_until_ready

FRAMES = 120
#: Larger than the link's jitter (at most 100 ms) and a busy machine's hiccups.
DELAY_MS = 250.0
#: As tests/test_recovery.py: a recorded frame showing the expected picture differs from it by
#: MP4 coding alone (3.1-3.3 grey levels over the face's box), another frame by 6 or more.
SAME_PICTURE = 4.5


@dataclass
class JitteryLink:
    """Publishes each packet 0 to 3 frames after it was made, in order; keeps what it sent."""

    link: LossyLink
    rng: random.Random = field(default_factory=lambda: random.Random(7))
    held: list[tuple[int, int, Any]] = field(default_factory=list)  # (release at, made at, packet)
    bursts: list[int] = field(default_factory=list)  # packets published together

    def frames(self, frames):
        for frame in self.link.frames(frames):
            self._release(frame.index)
            yield frame
        self._release(None)  # before the sender's Bye

    def __call__(self, packet: Any) -> None:
        self.held.append((self.link.seq + self.rng.randint(1, 3), self.link.seq, packet))

    def _release(self, seq: int | None) -> None:
        now, count = self.link.seq, 0
        while self.held and (seq is None or self.held[0][0] <= seq):
            _, self.link.seq, packet = self.held.pop(0)  # the link notes the packet's frame
            self.link(packet)
            count += 1
        self.link.seq = now
        self.bursts.append(count)


def _receiver(
    ports: tuple[int, int], output: str, keys: dict, display_fps: float | None, results: Any
) -> None:
    from facewire.receiver.playout import PlayoutSettings
    from facewire.receiver.session import ReceiverReport, RenderedFrame, run_receiver

    seen: list[tuple[int, int, float]] = []

    def sink(frame: RenderedFrame, report: ReceiverReport) -> None:
        seen.append((frame.seq, frame.capture_us, frame.latency_ms))

    try:
        report = run_receiver(
            HOST,
            *ports,
            output,
            join_timeout_s=JOIN_TIMEOUT_S,
            sink=sink,
            playout=PlayoutSettings(DELAY_MS, display_fps),
            **keys,
        )
        results.put(("ok", (report.as_dict(), seen)))
    except Exception as exc:
        results.put(("error", f"{type(exc).__name__}: {exc}"))


def call(
    tmp_path: Path,
    keys: Keys,
    drop=lambda seq: False,
    jitter: bool = False,
    display_fps: float | None = None,
):
    """A call of FRAMES frames through a lossy (and maybe jittery) link, shown at
    ``display_fps``; returns the link, the snapshot, the receiver's report, what its sink saw
    and its recording."""
    encoder, snapshot, frames = start_sender(FRAMES)
    output = tmp_path / "out.mp4"
    results = CTX.Queue()
    with SenderEndpoint(HOST, **keys.sender()) as endpoint:
        endpoint.set_snapshot(snapshot)
        process = CTX.Process(
            target=_receiver,
            args=(endpoint.ports, str(output), keys.receiver(), display_fps, results),
        )
        process.start()
        try:
            assert wait_until_ready(endpoint, JOIN_TIMEOUT_S, process.is_alive)
            link = LossyLink(endpoint, drop)
            if jitter:
                jittery = JitteryLink(link)
                run_sender(endpoint, encoder, jittery.frames(frames), publish=jittery)
            else:
                run_sender(endpoint, encoder, link.frames(frames), publish=link)
            status, detail = results.get(timeout=60)
        finally:
            process.join(timeout=10)
            if process.is_alive():
                process.kill()
    assert status == "ok", detail
    report, seen = detail
    return (jittery if jitter else link), link, snapshot, report, seen, read_video(output)


def frame_seqs(link: LossyLink) -> list[int]:
    """The frames whose packets the link passed on (REM patches left out)."""
    return [
        seq
        for seq, data in link.sent
        if seq not in link.lost and isinstance(decode(data), (KeyFrame, DeltaFrame))
    ]


def check_recording(snapshot, link: LossyLink, shown: list[int], video: list) -> None:
    """The recording is the screen, one picture per sender frame: frame i shows the newest
    frame shown at or before i (frames with no packet, lost or dropped as late hold).
    ``shown``: the sender's frames the sink saw, in order."""
    reference = reference_frames(snapshot, link.sent)
    box = face_box(reference)
    assert len(video) == FRAMES
    for i, image in enumerate(video):
        # (Frames before the first picture show it: see run_receiver.)
        expected = reference[max((s for s in shown if s <= i), default=shown[0])]
        assert mean_abs_diff(image[box], expected[box]) < SAME_PICTURE, i


@pytest.fixture
def keys(tmp_path: Path) -> Keys:
    return Keys(tmp_path)


def test_frames_that_come_in_bursts_are_shown_in_order_once_due(tmp_path: Path, keys: Keys) -> None:
    jittery, link, snapshot, report, seen, video = call(tmp_path, keys, jitter=True)
    assert max(jittery.bursts) >= 3 and jittery.bursts.count(0) > 10  # bursts and silences
    sent = frame_seqs(link)
    seqs = [seq for seq, _, _ in seen]
    instants = [instant for _, instant, _ in seen]
    # In capture order, each instant once; pictures between two frames (a frame before a
    # still stretch moving to the one after it) come in their place.
    assert seqs == sorted(seqs) and set(seqs) <= set(sent)
    assert all(a < b for a, b in zip(instants, instants[1:], strict=False))
    assert report["playout"]["mode"] == "delay 250 ms"
    # Every frame is shown, or counted as dropped because it came too late (a busy machine
    # falls behind the display's ticks).
    assert len(set(sent) - set(seqs)) == report["frames_skipped"] < len(sent) // 2
    # None is shown before it is due: the buffer's delay after the fastest path (one host:
    # the clocks agree, so that path takes 0 ms or more).
    assert min(latency for _, _, latency in seen) >= DELAY_MS
    check_recording(snapshot, link, seqs, video)


def test_a_gap_holds_the_picture_until_the_keyframe(tmp_path: Path, keys: Keys) -> None:
    gap = range(50, 62)
    # At twice the sender's rate every other picture lies between two frames: none may
    # between the frames either side of the gap.
    _, link, snapshot, report, seen, video = call(
        tmp_path, keys, drop=lambda s: s in gap, display_fps=60.0
    )
    seqs = [seq for seq, _, _ in seen]
    after = min(s for s in frame_seqs(link) if s >= gap.stop)
    # The last frame shown before the gap is shown once, as it is: the next picture is the
    # keyframe that ends the gap, or a frame after it. Nothing is guessed in between,
    # nothing blended across.
    before = max(s for s in seqs if s < gap.start)
    assert seqs.count(before) == 1 and seqs[seqs.index(before) + 1] >= after
    assert len(seqs) > len(set(seqs)) + 20  # pictures between frames elsewhere
    assert report["keyframe_requests"] > 0
    assert any(first <= gap.start < first + length for first, length in report["freezes"])
    # The recording holds the picture before the gap until the keyframe's.
    check_recording(snapshot, link, seqs, video)
