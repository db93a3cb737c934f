"""A room's participant cuts to another scene: its peers read the new scene's snapshot from
the room's bucket when its heartbeat names the new session, and draw the new scene from then
on in the same recording; never the old scene with the new face on it."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from facewire.protocol.clock import now_us
from facewire.protocol.media_path import DEFAULT_BUDGET_BPS
from facewire.protocol.sframe import RoomKey, Sealer, new_kid
from facewire.room_peer import RoomReceiver
from facewire.room_sender import RoomSender
from facewire.sender.capture import CapturedFrame
from facewire.sender.encoder import FaceEncoder
from facewire.sender.session import run_sender
from tests.call_helpers import read_video
from tests.cut_clip import BEFORE, bundled, off, slide, spliced
from tests.room_helpers import KeptLink

pytest.importorskip("cryptography")
FPS = 30.0


@dataclass
class Bucket(KeptLink):
    """A link that keeps every snapshot put, with how many messages had gone before it: the
    room's bucket as a peer reading it at a given message finds it."""

    puts: list[tuple[int, bytes]] = field(default_factory=list)

    def put_snapshot(self, data: bytes) -> None:
        super().put_snapshot(data)
        self.puts.append((len(self.messages), data))

    def at(self, message: int) -> bytes | None:
        """The bucket's snapshot once ``message`` messages had been published."""
        kept = [data for count, data in self.puts if count <= message]
        return kept[-1] if kept else None


def _paced(images: list[np.ndarray]) -> Iterator[CapturedFrame]:
    """The frames at a camera's pace: a new scene's session is built meanwhile, on a thread."""
    start = time.monotonic()
    for i, image in enumerate(images):
        time.sleep(max(0.0, start + i / FPS - time.monotonic()))
        yield CapturedFrame(i, image, now_us())


@pytest.fixture(scope="module")
def cut_stream() -> tuple[RoomKey, Bucket, list[np.ndarray]]:
    """Alice's sealed stream of the clip with a cut, sent as ``facewire room`` sends it."""
    key = RoomKey.generate("standup")
    frames = spliced()
    height, width = frames[0].shape[:2]
    encoder = FaceEncoder(width, height, FPS, refresh=False)
    snapshot = encoder.start(CapturedFrame(0, frames[0], now_us()), seq=0)
    assert snapshot is not None
    link = Bucket()
    sealer = Sealer(key.base_key("alice"), new_kid("alice"))
    endpoint = RoomSender(link, key, "alice", sealer, FPS, DEFAULT_BUDGET_BPS)  # type: ignore[arg-type]
    endpoint.set_snapshot(snapshot)
    report = run_sender(endpoint, encoder, _paced(frames))  # type: ignore[arg-type]
    assert report.scenes == 1 and len(link.puts) == 2
    return key, link, frames


def _receive(
    key: RoomKey, link: Bucket, record: Path, bucket: Callable[[int], bytes | None]
) -> tuple[RoomReceiver, list[str]]:
    """Carol receives Alice's messages one at a time, each handled (and any snapshot it
    made her read, from ``bucket(the message's index)``) before the next comes."""
    said: list[str] = []
    at = [0]  # the message being handled
    receiver = RoomReceiver(
        key, "carol", get_snapshot=lambda name: bucket(at[0]),
        publish=lambda subject, data: None, sealer=Sealer(key.base_key("carol"), new_kid("carol")),
        notify=said.append, record_dir=record,
    )  # fmt: skip
    try:
        for at[0], message in enumerate(link.messages):
            receiver.deliver(*message, now_us())
            deadline = time.monotonic() + 30.0
            while not receiver.inbox.empty() or receiver.joining:
                assert time.monotonic() < deadline, "timed out"
                receiver.run_once(0.01)
    finally:
        receiver.close()
    return receiver, said


def test_a_peer_s_new_scene_is_drawn_in_its_recording_from_its_own_snapshot(
    cut_stream: tuple, tmp_path: Path
) -> None:
    key, link, frames = cut_stream
    receiver, said = _receive(key, link, tmp_path, link.at)
    alice = receiver.figures["alice"]
    assert alice.sessions == 1 and alice.scenes == 1 and alice.left == "said bye", said
    assert alice.malformed == 0
    assert any(line.startswith("alice: a new scene from frame") for line in said), said
    rebuilt = read_video(tmp_path / "alice.mp4")
    first = alice.recorded_from
    # Frame i of the recording is the sender's frame first + i (gaps held, to the Bye's).
    assert first is not None and first + len(rebuilt) == len(frames)
    inputs = frames[first:]
    # Every picture after the cut is the old scene held or the new scene, and the new scene
    # from its first picture to the end.
    old = rebuilt[BEFORE - 1 - first]
    new = [off(rebuilt[i], inputs[i]) < 12.0 for i in range(BEFORE - first, len(inputs))]
    held = [off(rebuilt[i], old) < 2.0 for i in range(BEFORE - first, len(inputs))]
    assert all(a or b for a, b in zip(new, held, strict=True))
    assert True in new and all(new[new.index(True) :])


def test_a_new_scene_whose_snapshot_is_not_in_the_bucket_joins_the_peer_again(
    cut_stream: tuple, tmp_path: Path
) -> None:
    """The bucket still gives the old snapshot when the heartbeat names the new session (a
    stale replica): the peer leaves and is joined again as a newcomer from its next message,
    whose snapshot is the new one; the new scene goes to a recording of its own."""
    key, link, frames = cut_stream
    stale = {"reads": 0}

    def bucket(message: int) -> bytes | None:
        stale["reads"] += 1
        return link.puts[0][1] if stale["reads"] == 2 else link.at(message)

    receiver, said = _receive(key, link, tmp_path, bucket)
    alice = receiver.figures["alice"]
    assert alice.sessions == 2 and alice.scenes == 0 and alice.left == "said bye", said
    assert any("alice left (its new scene cannot be shown" in line for line in said), said
    again = read_video(tmp_path / "alice.2.mp4")
    assert again and off(again[-1], frames[-1]) < 12.0


def test_a_peer_who_begins_with_no_face_is_drawn_as_its_scene_then_its_face(
    tmp_path: Path,
) -> None:
    """Alice's camera shows a slide, then her face: her call begins with a session of the
    scene alone (her face kept outside the frame), and the peer draws the slide with no face
    on it, then her face's session as a new scene of hers."""
    key = RoomKey.generate("standup")
    frames = slide(30) + bundled(45)
    encoder = FaceEncoder(640, 480, FPS, refresh=False)
    snapshot = encoder.start_without_face(CapturedFrame(0, frames[0], now_us()), seq=0)
    link = Bucket()
    sealer = Sealer(key.base_key("alice"), new_kid("alice"))
    endpoint = RoomSender(link, key, "alice", sealer, FPS, DEFAULT_BUDGET_BPS)  # type: ignore[arg-type]
    endpoint.set_snapshot(snapshot)
    report = run_sender(endpoint, encoder, _paced(frames))  # type: ignore[arg-type]
    assert report.scenes == 1
    receiver, said = _receive(key, link, tmp_path, link.at)
    alice = receiver.figures["alice"]
    assert alice.sessions == 1 and alice.scenes == 1 and alice.left == "said bye", said
    rebuilt = read_video(tmp_path / "alice.mp4")
    first = alice.recorded_from
    assert first is not None and first + len(rebuilt) == len(frames)
    inputs = frames[first:]
    cut = 30 - first
    assert all(off(rebuilt[i], inputs[i]) < 3.0 for i in range(cut))  # the slide alone
    new = [off(rebuilt[i], inputs[i]) < 12.0 for i in range(cut, len(inputs))]
    assert True in new and new.index(True) < FPS and all(new[new.index(True) :])
