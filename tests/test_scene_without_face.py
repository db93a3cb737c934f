"""A scene with no face: a cut to a slide, a person who leaves. The sender starts a session of
the scene alone, and one of the face when a face comes; the receiver draws the scene, never
a face over it."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.loopback import Loopback
from facewire.protocol.constants import FACE
from facewire.protocol.packets import Snapshot
from facewire.receiver.decoder import FaceDecoder, shows_face
from facewire.sender.capture import CapturedFrame
from facewire.sender.encoder import FaceEncoder
from facewire.sender.scene_cut import FACE_FOUND_FRAMES, FACE_LOST_S, NO_FACE_AFTER_S
from tests.cut_clip import FIXTURE, bundled, demo_call, off, slide

FPS = 30.0
#: Frames of the bundled clip before the cut, of the slide, and of the bundled clip again.
BEFORE, SLIDE, AGAIN = 30, 45, 30


def _cut_to_slide_and_back() -> list[np.ndarray]:
    frames = bundled(BEFORE + AGAIN)
    return frames[:BEFORE] + slide(SLIDE) + frames[BEFORE:]


def _call(frames: list[np.ndarray]) -> tuple[list[np.ndarray], list[Snapshot], FaceEncoder]:
    """Pictures of a loopback call on ``frames``, the snapshots of its new scenes as the
    receiver decoded them, and the encoder."""
    encoder = FaceEncoder(640, 480, FPS)
    pictures, snapshots = [], []
    with Loopback(encoder, CapturedFrame(0, frames[0], 0)) as both:
        for i, image in enumerate(frames):
            scenes = both.scenes
            both.step(CapturedFrame(i, image, round(i * 1e6 / FPS)))
            if both.scenes > scenes:
                snapshots.append(both.snapshot)
            pictures.append(both.picture())
    return pictures, snapshots, encoder


@pytest.fixture(scope="module")
def slide_call() -> tuple[list[np.ndarray], list[np.ndarray], list[Snapshot], FaceEncoder]:
    frames = _cut_to_slide_and_back()
    return (frames, *_call(frames))


def test_a_cut_to_a_slide_shows_the_slide_and_no_face(slide_call: tuple) -> None:
    frames, pictures, snapshots, _ = slide_call
    assert len(snapshots) == 2  # the slide, then the face again
    alone = snapshots[0]
    assert not shows_face(alone) and alone.meta[FACE] == 0 and alone.texture == b""
    assert BEFORE <= alone.seq <= BEFORE + round(NO_FACE_AFTER_S * FPS) + 1
    # From its snapshot frame to the next cut the slide is drawn, with no face on it.
    for i in range(alone.seq, BEFORE + SLIDE):
        assert off(pictures[i], frames[i]) < 3.0, i
    # Before it the old picture stays (the old scene's last one, not a face over the slide).
    for i in range(BEFORE, alone.seq):
        assert off(pictures[i], pictures[BEFORE - 1]) < 2.0, i


def test_a_face_after_the_slide_begins_a_session_of_it(slide_call: tuple) -> None:
    frames, pictures, snapshots, encoder = slide_call
    face = snapshots[1]
    assert shows_face(face) and face.texture
    assert BEFORE + SLIDE <= face.seq <= BEFORE + SLIDE + round(NO_FACE_AFTER_S * FPS) + 1
    assert not encoder.faceless
    for i in range(face.seq, face.seq + 10):
        assert off(pictures[i], frames[i]) < 6.0, i


def test_the_scene_alone_is_drawn_exactly_from_its_snapshot(slide_call: tuple) -> None:
    """Its face is outside the frame: the snapshot frame's values draw the background itself,
    and no texture is asked for (a receiver would say it shows grey)."""
    _, _, snapshots, _ = slide_call
    decoder = FaceDecoder(snapshots[0])
    try:
        picture = decoder.reconstruct(decoder.reference)
        assert off(picture, decoder.background) < 0.5
    finally:
        decoder.close()


def test_no_texture_is_said_missing_for_a_scene_without_a_face(
    slide_call: tuple, caplog: pytest.LogCaptureFixture
) -> None:
    _, _, snapshots, _ = slide_call
    with caplog.at_level(logging.WARNING, logger="facewire.receiver.decoder"):
        FaceDecoder(snapshots[0]).close()
    assert "no texture" not in caplog.text


def test_a_person_who_leaves_is_no_face_left_over_the_scene() -> None:
    """The face hidden for longer than FACE_LOST_S (the person left the room, or the camera
    turned away): a session of the scene alone, then one of the face when it is back."""
    frames = bundled(30 + 45 + 30)
    gone = range(30, 75)
    for i in gone:
        cv2.ellipse(frames[i], (330, 230), (140, 190), 0, 0, 360, (90, 120, 160), -1)
    pictures, snapshots, encoder = _call(frames)
    assert [shows_face(s) for s in snapshots] == [False, True]
    lost = round(FACE_LOST_S * FPS)
    assert gone[0] + lost - 1 <= snapshots[0].seq <= gone[0] + lost + 1
    for i in range(snapshots[0].seq, gone[-1] + 1):
        assert off(pictures[i], frames[i]) < 3.0, i  # the hiding ellipse, no face drawn
    assert gone[-1] < snapshots[1].seq <= gone[-1] + FACE_FOUND_FRAMES + 2
    assert off(pictures[-1], frames[-1]) < 12.0
    assert encoder.frames_untracked == lost  # until then, the face held where it was


def test_a_face_hidden_for_a_moment_stays_in_its_session() -> None:
    frames = bundled(60)
    for i in range(20, 20 + round(FACE_LOST_S * FPS) // 2):
        cv2.ellipse(frames[i], (330, 230), (140, 190), 0, 0, 360, (90, 120, 160), -1)
    _, snapshots, _ = _call(frames)
    assert snapshots == []


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[list[np.ndarray], list, dict]:
    """``facewire demo`` (two processes, ZeroMQ on loopback, EGL) on a cut to a slide and
    back."""
    return demo_call(tmp_path_factory.mktemp("faceless"), _cut_to_slide_and_back())


def test_a_call_shows_the_slide_then_the_face_again(demo: tuple) -> None:
    inputs, rebuilt, stats = demo
    assert stats["ended_by"] == "bye" and stats["malformed"] == 0
    assert stats["scenes"] == 2 and len(stats["scene_first_s"]) == 2
    assert len(rebuilt) == len(inputs)
    # Each scene comes within a second of its cut; until then the picture before it stays.
    for cut in (BEFORE, BEFORE + SLIDE):
        held = rebuilt[cut - 1]
        new = [off(rebuilt[i], inputs[i]) < 6.0 for i in range(cut, cut + round(FPS))]
        first = new.index(True)
        assert all(off(rebuilt[i], held) < 2.0 for i in range(cut, cut + first))
        assert all(new[first : first + 10])


@pytest.mark.parametrize("tail", [12, 3])
def test_a_face_in_the_last_half_second_of_a_file_is_still_shown(tmp_path: Path, tail: int) -> None:
    """The face comes ``tail`` frames before the input ends: the sender said Bye before its
    receiver had the new session's snapshot (a draft waits for its datagrams' path), and the
    receiver waited for it until its join timeout, the face never shown; or, its session
    still being built when the input ended, never served it. It is served, and the receiver
    answered, before the Bye."""
    frames = slide(40) + bundled(tail)
    inputs, rebuilt, stats = demo_call(tmp_path, frames)
    assert stats["ended_by"] == "bye" and stats["scenes"] == 1
    assert len(rebuilt) == len(inputs) == len(frames)
    assert off(rebuilt[-1], inputs[-1]) < 6.0


def test_a_better_view_whose_face_then_goes_ends_in_the_scene_alone() -> None:
    """The face was seen far better than in its snapshot (a new session due), and then no
    face is found to start it from (foreman, his face panned out of view): the frames are not
    sent meanwhile, as for any new scene, and once the face has been gone FACE_LOST_S the
    scene alone is. (The sender sent nothing for foreman's last 4 s, and his receiver
    refused the Bye so far on.) Driven as ``run_sender`` drives it."""
    frames = bundled(80)
    for image in frames[20:]:
        cv2.ellipse(image, (330, 230), (140, 190), 0, 0, 360, (90, 120, 160), -1)
    encoder = FaceEncoder(640, 480, FPS)
    assert encoder.start(CapturedFrame(0, frames[0], 0)) is not None
    started = None
    for i, image in enumerate(frames[1:], start=1):
        frame = CapturedFrame(i, image, round(i * 1e6 / FPS))
        if i == 20:
            encoder._new_scene = encoder._better = True  # as BetterView.seen says it
        if encoder.scene_changed(frame):
            snapshot = encoder.start_scene(frame)
            if snapshot is not None and started is None:
                started = snapshot
            continue  # not sent: run_sender skips it
        encoder.encode(frame)
    assert started is not None and not shows_face(started)
    assert abs(started.seq - (20 + round(FACE_LOST_S * FPS))) <= 1


def test_a_face_seen_a_moment_in_a_scene_without_one_leaves_that_scene_going_on() -> None:
    """In a session of the scene alone a face is tracked FACE_FOUND_FRAMES running and is gone
    on the next frame, which its session would have been started from: the scene alone goes
    on, its frames sent, and no session is started (a session looked for on every frame, none
    sent)."""
    frames = slide(60)
    face = cv2.resize(cv2.imread(str(FIXTURE)), (200, 200))
    # No cut: a face on a poster held up (the tracker finds it from its second frame).
    for image in frames[20 : 21 + FACE_FOUND_FRAMES]:
        image[260:460, 420:620] = face
    encoder = FaceEncoder(640, 480, FPS)
    encoder.start_without_face(CapturedFrame(0, frames[0], 0))
    sent, started = 0, 0
    for i, image in enumerate(frames[1:], start=1):
        frame = CapturedFrame(i, image, round(i * 1e6 / FPS))
        if encoder.scene_changed(frame):
            started += encoder.start_scene(frame) is not None
            continue  # not sent: run_sender skips it
        encoder.encode(frame)
        sent += 1
    assert encoder.faceless and started == 0
    assert sent == len(frames) - 2  # the one its session was to start from
