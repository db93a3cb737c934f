"""The fit residual the sender reports per frame (sender/fit_residual.py)."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path
from facewire.sender.encoder import FaceEncoder
from facewire.sender.fit_residual import FitResidual, rms_px

FRAMES = 40


@pytest.fixture(scope="module")
def frames() -> list[CapturedFrame]:
    with VideoSource(demo_clip_path()) as video:
        return [
            CapturedFrame(f.index, f.image, round(f.index * 1e6 / video.fps))
            for f in video.frames(limit=FRAMES)
        ]


def _residual(frames: list[CapturedFrame], error_px: float) -> FitResidual:
    encoder = FaceEncoder(640, 480, 30.0, rem=False, error_px=error_px)
    assert encoder.start(frames[0]) is not None
    for frame in frames:
        encoder.encode(frame)
    return encoder.residual


def test_rms_px_is_the_image_plane_distance() -> None:
    a = np.zeros((4, 3))
    b = np.array([[3.0, 4.0, 9.0]] * 2 + [[0.0, 0.0, -7.0]] * 2)  # z never counts
    assert rms_px(a, b) == pytest.approx(np.sqrt(25 / 2))


def test_coarser_steps_move_the_sent_face_not_the_fit(frames) -> None:
    fine, coarse = _residual(frames, 0.4), _residual(frames, 6.0)
    assert len(fine) == len(coarse) == FRAMES
    # The wire fit does not depend on the coding ...
    assert np.allclose(fine.fit, coarse.fit, atol=1e-4)
    # ... the face sent does: 6 px steps leave it further from what the tracker saw (1.6 px
    # median at 0.4, 3.6 at 6; 4 px steps left 1.9 once the face was moved by
    # sender/synthesis.py, whose moves the basis and smoothing keep only in part).
    assert np.median(coarse.sent) > np.median(fine.sent) + 0.5
    summary = fine.summary()
    assert summary["frames"] == FRAMES
    assert summary["sent_px"]["median"] == pytest.approx(float(np.median(fine.sent)))
    assert summary["per_frame"][0][0] == 0 and len(summary["per_frame"]) == FRAMES


def test_no_tracked_frame_reports_nothing() -> None:
    summary = FitResidual().summary()
    assert summary == {"frames": 0, "fit_px": None, "sent_px": None, "per_frame": []}
