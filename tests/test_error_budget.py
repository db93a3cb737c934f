"""The sender's error budget for a large face: no finer than the landmark tracker resolves."""

from __future__ import annotations

import cv2
import pytest

from facewire.models.face_channels import DEFAULT_ERROR_PX, channel_steps
from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path
from facewire.sender.encoder import TRACKER_RESOLUTION_SHARE, FaceEncoder


def _first_frame(size: tuple[int, int] | None = None) -> CapturedFrame:
    with VideoSource(demo_clip_path()) as video:
        image = next(iter(video.frames(limit=1))).image
    if size is not None:
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return CapturedFrame(0, image, 0)


def test_a_large_face_is_coded_as_finely_as_the_tracker_resolves() -> None:
    # The bundled clip's face is about 223 px high: one pixel of the landmark model's 192-px
    # input (1.5 times the face) is 1.74 image pixels, so the budget rises above 0.4 px and
    # every step with it.
    frame = _first_frame()
    encoder = FaceEncoder(640, 480, 30.0, rem=False)
    assert encoder.start(frame) is not None
    assert encoder.budget_px == pytest.approx(TRACKER_RESOLUTION_SHARE * 1.5 * 223 / 192, 0.05)
    assert encoder.budget_px > DEFAULT_ERROR_PX
    # The steps (a translation step is the budget in pixels) and the snapshot follow it.
    translation = channel_steps(1.0, 1.0, encoder.budget_px)["pose.translation"]
    assert encoder.steps["pose.translation"] == pytest.approx(translation)


def test_a_small_face_keeps_the_budget_asked_for() -> None:
    # The same frame at QCIF size: a 55-px face, a model pixel of 0.43 image pixels.
    encoder = FaceEncoder(176, 132, 30.0, rem=False)
    assert encoder.start(_first_frame((176, 132))) is not None
    assert encoder.budget_px == DEFAULT_ERROR_PX
    asked = FaceEncoder(176, 132, 30.0, rem=False, error_px=0.3)
    asked.start(_first_frame((176, 132)))
    assert asked.budget_px == 0.3
