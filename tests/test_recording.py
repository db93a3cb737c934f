"""The receiver's recording on its own thread: every frame in order, a playable file on close."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_call import count_frames

from facewire.quality import read_frames, ssim
from facewire.receiver.recorder import SMALL_PIXELS, Mp4Recorder
from facewire.receiver.recording import BackgroundRecorder

FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"


def test_every_frame_is_written_in_order_and_the_file_is_closed(tmp_path: Path) -> None:
    path = tmp_path / "out.mp4"
    levels = [(i * 37) % 256 for i in range(90)]
    with BackgroundRecorder(path, 64, 48, 30.0) as recorder:
        for level in levels:
            recorder.write(np.full((48, 64, 3), level, np.uint8))
        assert recorder.frames == 90
    assert count_frames(path) == 90
    got = [int(round(float(frame.mean()))) for frame in read_frames(path)]
    # The codec shifts flat grey by a few levels; a frame out of place
    # would be off by 37 or more.
    assert np.abs(np.array(got) - np.array(levels)).max() <= 6


def test_a_wrong_size_is_refused_at_once(tmp_path: Path) -> None:
    with BackgroundRecorder(tmp_path / "out.mp4", 64, 48, 30.0) as recorder:
        with pytest.raises(ValueError, match="expected a 64x48 frame"):
            recorder.write(np.zeros((48, 63, 3), np.uint8))
        recorder.write(np.zeros((48, 64, 3), np.uint8))
    assert count_frames(tmp_path / "out.mp4") == 1


def test_a_failing_writer_is_reported(tmp_path: Path) -> None:
    recorder = BackgroundRecorder(tmp_path / "out.mp4", 64, 48, 30.0)
    recorder.write(np.zeros((48, 64, 3), np.float32))  # the encoder thread cannot take it
    with pytest.raises(OSError, match="recording .*out.mp4 failed"):
        recorder.close()


def test_a_small_call_is_recorded_without_losing_its_face(tmp_path: Path) -> None:
    """At 176x144 a face is a few 8x8 blocks: MPEG-4 at its fine quantiser kept 0.990 SSIM
    of this picture, H.264 keeps 0.995 (and the benchmarks' face scores with it)."""
    import av
    import cv2

    picture = cv2.resize(cv2.imread(str(FIXTURE)), (176, 144), interpolation=cv2.INTER_AREA)
    assert 176 * 144 <= SMALL_PIXELS
    frames = [np.roll(picture, i, axis=1) for i in range(10)]  # a slow pan
    with Mp4Recorder(tmp_path / "small.mp4", 176, 144, 30.0) as recorder:
        for frame in frames:
            recorder.write(frame)
    with av.open(str(tmp_path / "small.mp4")) as container:
        assert container.streams.video[0].codec_context.name == "h264"
    got = list(read_frames(tmp_path / "small.mp4"))
    assert len(got) == len(frames)
    assert min(ssim(f, g) for f, g in zip(frames, got, strict=True)) > 0.994
    with Mp4Recorder(tmp_path / "large.mp4", 640, 480, 30.0) as recorder:
        recorder.write(cv2.resize(picture, (640, 480)))
    with av.open(str(tmp_path / "large.mp4")) as container:
        assert container.streams.video[0].codec_context.name == "mpeg4"
