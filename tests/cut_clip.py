"""A clip with a cut: the bundled clip, then another shot (a photographed face on a wall)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from facewire.sender.capture import VideoSource, demo_clip_path

FIXTURE = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"
BEFORE, AFTER = 30, 150  # frames of the bundled clip, then of the other scene (5 s: its session
# takes a second to start on a busy machine, seconds on a very busy one)


def bundled(count: int) -> list[np.ndarray]:
    with VideoSource(demo_clip_path()) as video:
        return [f.image for f in video.frames(limit=count)]


def other_scene(count: int, size: tuple[int, int] = (640, 480)) -> list[np.ndarray]:
    """Another shot: a photographed astronaut on a flat wall, the camera's noise on it."""
    face = cv2.imread(str(FIXTURE))
    width, height = size
    canvas = np.full((height, width, 3), (70, 120, 150), np.uint8)
    m = cv2.getRotationMatrix2D((210, 210), 0.0, height / 420 * 0.9)
    m[:, 2] += (width / 2 - 210, height / 2 - 210)
    cv2.warpAffine(face, m, size, dst=canvas, borderMode=cv2.BORDER_TRANSPARENT)
    rng = np.random.default_rng(5)
    noisy = [canvas.astype(np.int16) + rng.integers(-2, 3, canvas.shape) for _ in range(count)]
    return [np.clip(f, 0, 255).astype(np.uint8) for f in noisy]


def spliced() -> list[np.ndarray]:
    return bundled(BEFORE) + other_scene(AFTER)


def off(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two pictures, grey levels."""
    return float(np.abs(a.astype(int) - b.astype(int)).mean())
