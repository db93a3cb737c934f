"""Hands held up near the face, found by MediaPipe's palm detector (the lite model).

The refreshes (sender/refresh.py) cut nothing new where the warp carries the picture with a
moving head: there an area fixed in the frame goes stale as the head moves on. A hand held
up beside a moving head is the exception that a person sees at once: it stays where it is
while the head moves. The palm detector says where hands are (about 4 ms, every fourth
frame, half-way between the refreshes' comparisons, around the face); a palm found twice
running in much the same place is held, and the refreshes may cut it whatever the head does.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facewire.models.network import Network, rgb_input
from facewire.sender.detector import (
    box_iou,
    decode,
    model_path,
    square_input,
    ssd_anchors,
    weighted_nms,
)

INPUT_SIZE = 192
#: A palm's score (0-1) from which it counts (MediaPipe's own threshold).
MIN_SCORE = 0.5
#: Boxes overlapping more than this (intersection over union) are one palm.
NMS_IOU = 0.3
#: A palm found again overlapping its last box at least this much has been held in place.
HELD_IOU = 0.3
#: The whole hand around a palm, as MediaPipe's hand tracking crops it: a square this many
#: times the palm box's larger side ...
HAND_SCALE = 2.6
#: ... its centre moved this share of that side from the palm's towards the fingers (from
#: the wrist to the middle finger's root, the detector's first and third hand points).
HAND_SHIFT = 0.5


@dataclass(frozen=True)
class Hand:
    """A hand found: its palm's box (the palm and the fingers' roots) and the square around
    the whole hand, (x0, y0, x1, y1) in the frame's pixels. The detector takes some faces for
    palms (carphone's, Claire's): a palm whose centre is on the face is left to the caller."""

    palm: np.ndarray
    box: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        return (self.palm[:2] + self.palm[2:]) / 2


class PalmDetector:
    """Hands in a frame, found by their palms."""

    def __init__(self, path: str | Path | None = None) -> None:
        self.net = Network(
            Path(path) if path is not None else model_path("palm_detection_lite.tflite")
        )
        self.anchors = ssd_anchors(INPUT_SIZE)

    def detect(
        self, frame_bgr: np.ndarray, around: tuple[float, float, float] | None = None
    ) -> list[Hand]:
        """The hands in ``frame_bgr`` ((h, w, 3) uint8 BGR, any size), best first; only in the
        square ``around`` (centre x, centre y, side, pixels) when it is smaller than the frame:
        a hand there is larger in the network's 192 pixels."""
        h, w = frame_bgr.shape[:2]
        corner = np.zeros(2)
        if around is not None and around[2] < max(h, w):
            frame_bgr, corner = _square(frame_bgr, *around)
        small, side, offset = square_input(frame_bgr, INPUT_SIZE)
        offset = offset - corner
        out = self.net.run(rgb_input(small, 1 / 255.0))
        # Two outputs, told apart by their last axis: 18 regressors a box, one score logit.
        regressors, logits = sorted(out.values(), key=lambda a: a.shape[-1], reverse=True)
        boxes, points, scores = decode(regressors[0], logits.reshape(-1), self.anchors, INPUT_SIZE)
        keep = scores >= MIN_SCORE
        if not keep.any():
            return []
        hands = []
        for box, hand, _ in weighted_nms(boxes[keep], points[keep], scores[keep], NMS_IOU):
            palm = box * side - 0.5 - np.tile(offset, 2)
            towards = (hand[2] - hand[0]) * side
            towards /= max(float(np.hypot(*towards)), 1e-9)
            size = float(max(palm[2] - palm[0], palm[3] - palm[1]))
            centre = (palm[:2] + palm[2:]) / 2 + HAND_SHIFT * size * towards
            half = HAND_SCALE * size / 2
            hands.append(Hand(palm, np.r_[centre - half, centre + half]))
        return hands


def _square(
    frame_bgr: np.ndarray, cx: float, cy: float, side: float
) -> tuple[np.ndarray, np.ndarray]:
    """The square of ``side`` around (cx, cy) from ``frame_bgr``, black beyond its edges, and
    the square's top-left corner in the frame."""
    h, w = frame_bgr.shape[:2]
    n = max(1, round(side))
    x0, y0 = round(cx - n / 2), round(cy - n / 2)
    out = np.zeros((n, n, 3), np.uint8)
    fx0, fy0, fx1, fy1 = max(0, x0), max(0, y0), min(w, x0 + n), min(h, y0 + n)
    if fx1 > fx0 and fy1 > fy0:
        out[fy0 - y0 : fy1 - y0, fx0 - x0 : fx1 - x0] = frame_bgr[fy0:fy1, fx0:fx1]
    return out, np.array([x0, y0], dtype=np.float64)


class HeldPalms:
    """The hands held in place: found at this look and the one before, overlapping."""

    def __init__(self, detector: PalmDetector | None = None) -> None:
        self.detector = detector if detector is not None else PalmDetector()
        self._last: list[Hand] = []

    def update(
        self, frame_bgr: np.ndarray, around: tuple[float, float, float] | None = None
    ) -> list[Hand]:
        found = self.detector.detect(frame_bgr, around)
        last = np.array([c.palm for c in self._last]).reshape(-1, 4)
        held = [h for h in found if (box_iou(h.palm, last) >= HELD_IOU).any()]
        self._last = found
        return held
