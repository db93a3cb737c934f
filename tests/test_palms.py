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


def test_a_small_hand_by_a_small_face_is_found_looking_around_the_face(
    detector: PalmDetector, hands: np.ndarray
) -> None:
    """A 72-px face with a hand beside it in a 1280x720 frame: the hand is under 45 of the
    network's 192 pixels on the whole frame and is missed; looked for in a square four face
    widths wide around the face (sender/refresh.py's HAND_LOOK) it is found, and its box is
    where it is in the frame."""
    photo = cv2.resize(
        cv2.imread(str(FIXTURES / "astronaut_face.jpg")), (320, 320), interpolation=cv2.INTER_AREA
    )
    hand = cv2.resize(hands[:, 50:345], None, fx=0.25, fy=0.25, interpolation=cv2.INTER_AREA)
    keep = ~(hand.min(axis=2) > 225)
    photo[36 : 36 + hand.shape[0], 186 : 186 + hand.shape[1]][keep] = hand[keep]
    frame = cv2.resize(cv2.imread(str(FIXTURES / "astronaut_face.jpg")), (1280, 1280))[280:1000]
    frame[200:520, 480:800] = photo  # the face's centre at (640, 293)
    assert detector.detect(frame) == []
    found = detector.detect(frame, (640.0, 293.0, 4 * 72.0))
    assert len(found) == 1, found
    rows, cols = np.nonzero(keep)
    x0, y0, x1, y1 = found[0].box
    inside = (x0 <= 666 + cols) & (666 + cols < x1) & (y0 <= 236 + rows) & (236 + rows < y1)
    assert inside.mean() > 0.9, (found[0].box, inside.mean())
