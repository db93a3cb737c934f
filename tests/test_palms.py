"""The palm detector (sender/palms.py): hands held up are found, a face alone is no hand, and a
hand counts as held once it is found twice in much the same place."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from facewire.sender.palms import HeldPalms, PalmDetector

FIXTURES = Path(__file__).parent / "fixtures"


@pytest.fixture(scope="module")
def detector() -> PalmDetector:
    return PalmDetector()


@pytest.fixture(scope="module")
def hands() -> np.ndarray:
    return cv2.imread(str(FIXTURES / "hands.jpg"))


def test_two_hands_held_up_are_found_whole(detector: PalmDetector, hands: np.ndarray) -> None:
    """hands.jpg: a left hand, fingers up (x 55-340), and a right one, fingers down (x
    380-700). Each is found, and its box is the whole hand's, fingers too, not the palm's."""
    found = sorted((h.box for h in detector.detect(hands)), key=lambda box: box[0])
    assert len(found) == 2, found
    left, right = found
    for box, (x0, x1) in ((left, (55, 340)), (right, (380, 700))):
        assert box[0] <= x0 + 20 and box[2] >= x1 - 20, box
    # The left hand's fingertips are near the top, the right one's near the bottom.
    assert left[1] <= 20 and left[3] >= 360, left
    assert right[3] >= 350, right


def test_a_face_alone_is_no_hand(detector: PalmDetector) -> None:
    from facewire.sender.capture import VideoSource, demo_clip_path

    assert detector.detect(cv2.imread(str(FIXTURES / "astronaut_face.jpg"))) == []
    with VideoSource(demo_clip_path()) as video:
        for frame in video.frames(limit=30):
            assert detector.detect(frame.image) == []


def test_a_hand_is_held_once_found_twice_in_much_the_same_place(
    detector: PalmDetector, hands: np.ndarray
) -> None:
    h, w = hands.shape[:2]
    here = np.full((2 * h, 2 * w, 3), 255, np.uint8)
    there = here.copy()
    here[:h, :w] = hands
    there[h:, w:] = hands  # both moved half the picture's size away
    held = HeldPalms(detector)
    assert held.update(here) == []  # seen once
    assert len(held.update(here)) == 2
    assert len(detector.detect(there)) == 2
    assert held.update(there) == []
    assert len(held.update(there)) == 2
