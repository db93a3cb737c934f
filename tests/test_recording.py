"""The receiver's recording on its own thread: every frame in order, a playable file on close."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from cli_call import count_frames

from facewire.quality import read_frames
from receiver.recording import BackgroundRecorder


def test_every_frame_is_written_in_order_and_the_file_is_closed(tmp_path: Path) -> None:
    path = tmp_path / "out.mp4"
    levels = [(i * 37) % 256 for i in range(90)]
    with BackgroundRecorder(path, 64, 48, 30.0) as recorder:
        for level in levels:
            recorder.write(np.full((48, 64, 3), level, np.uint8))
        assert recorder.frames == 90
    assert count_frames(path) == 90
    got = [int(round(float(frame.mean()))) for frame in read_frames(path)]
    # mp4v at its default quality shifts flat grey by a few levels; a frame out of place
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
