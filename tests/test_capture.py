"""A file read at its frame rate, as a camera gives frames: a reader that falls behind gets
the newest frame, the ones it had no time for are left out, and the numbers go on."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.call import MAX_SIZE, _Source
from facewire.sender.capture import BEHIND_FRAMES, VideoSource

FPS = 30.0
FRAMES = 24


@pytest.fixture(scope="module")
def clip(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("capture") / "count.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), FPS, (64, 48))
    for i in range(FRAMES):
        writer.write(np.full((48, 64, 3), 10 * i, np.uint8))
    writer.release()
    return path


def test_a_reader_behind_gets_the_newest_frame_and_keeps_real_time(clip: Path) -> None:
    with VideoSource(clip, realtime=True) as video:
        start = time.monotonic()
        seen = []
        for frame in video.frames():
            seen.append(frame.index)
            time.sleep(2.5 / FPS)  # a sender that takes two and a half frames' time for each
        elapsed = time.monotonic() - start
    assert video.dropped > 0 and len(seen) + video.dropped == FRAMES
    assert seen == sorted(set(seen)) and seen[0] == 0
    # The frames read keep the file's pace: never more than BEHIND_FRAMES behind.
    assert 0 <= elapsed - 2.5 / FPS - seen[-1] / FPS < (BEHIND_FRAMES + 1) / FPS


def test_a_looped_file_numbers_on_past_the_frames_left_out(clip: Path) -> None:
    args = argparse.Namespace(
        frames=3 * FRAMES, camera=None, input=str(clip), loop=True, max_size=MAX_SIZE
    )
    source = _Source(args)
    try:
        seen = []
        for frame in source.frames():
            seen.append(frame.index)
            time.sleep(1.6 / FPS)
    finally:
        source.close()
    # Each loop's frames follow the last one's, whichever were left out, and --frames counts
    # the input's frames: three loops.
    assert seen == sorted(set(seen)) and seen[-1] < 3 * FRAMES <= seen[-1] + source.dropped + 1
    assert source.dropped > 0 and len(seen) + source.dropped == 3 * FRAMES


def test_a_phone_video_held_upright_is_read_upright(tmp_path: Path) -> None:
    """A phone held upright stores its picture on its side, with a display matrix saying to
    turn it (MP4's rotation): the sender reads it as the phone showed it, portrait, or the
    face lies on its side and no face is found."""
    import av

    portrait = np.full((96, 64, 3), 40, np.uint8)
    portrait[8:24, 8:24] = 250  # a mark at the top left, as the phone showed it
    path = tmp_path / "phone.mp4"
    with av.open(str(path), "w", format="mp4") as out:
        stream = out.add_stream("libx264", rate=30)
        stream.width, stream.height, stream.pix_fmt = 96, 64, "yuv420p"
        stream.set_display_rotation(90)  # stored turned a quarter clockwise
        stored = np.ascontiguousarray(cv2.rotate(portrait, cv2.ROTATE_90_CLOCKWISE))
        for _ in range(3):
            out.mux(stream.encode(av.VideoFrame.from_ndarray(stored, format="bgr24")))
        out.mux(stream.encode())
    with VideoSource(path) as video:
        first = next(iter(video.frames())).image
    assert first.shape == portrait.shape
    assert np.abs(first.astype(int) - portrait).mean() < 6
