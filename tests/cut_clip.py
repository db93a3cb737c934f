"""A clip with a cut: the bundled clip, then another shot (a photographed face on a wall, or a
slide with no face on it)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from facewire.cli import main
from facewire.sender.capture import VideoSource, demo_clip_path
from tests.call_helpers import read_video

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


def slide(count: int, size: tuple[int, int] = (640, 480)) -> list[np.ndarray]:
    """A shot with no face: a slide of boxes and lines of text, the camera's noise on it."""
    width, height = size
    canvas = np.full((height, width, 3), (235, 240, 238), np.uint8)
    cv2.rectangle(canvas, (0, 0), (width, height // 6), (120, 60, 20), -1)
    cv2.putText(canvas, "Quarterly figures", (width // 20, height // 9),
                cv2.FONT_HERSHEY_DUPLEX, height / 400, (255, 255, 255), 2)  # fmt: skip
    for k in range(6):
        y = height // 4 + k * height // 10
        line = f"- item {k + 1}: {17 * (k + 3)} units, up {k + 2} %"
        cv2.putText(canvas, line, (width // 12, y), cv2.FONT_HERSHEY_SIMPLEX, height / 700,
                    (40, 40, 40), 1)  # fmt: skip
    for k, colour in enumerate([(60, 140, 220), (80, 180, 90), (200, 120, 60)]):
        x = width * 2 // 3 + k * width // 12
        cv2.rectangle(canvas, (x, height * (8 - 2 * k) // 10), (x + width // 16, height * 9 // 10),
                      colour, -1)  # fmt: skip
    rng = np.random.default_rng(7)
    noisy = [canvas.astype(np.int16) + rng.integers(-2, 3, canvas.shape) for _ in range(count)]
    return [np.clip(f, 0, 255).astype(np.uint8) for f in noisy]


def spliced() -> list[np.ndarray]:
    return bundled(BEFORE) + other_scene(AFTER)


def off(a: np.ndarray, b: np.ndarray) -> float:
    """Mean absolute difference of two pictures, grey levels."""
    return float(np.abs(a.astype(int) - b.astype(int)).mean())


def demo_call(
    folder: Path, frames: list[np.ndarray], fps: float = 30.0
) -> tuple[list[np.ndarray], list[np.ndarray], dict[str, Any]]:
    """``facewire demo`` (two processes, ZeroMQ on loopback, EGL) on ``frames`` written as an
    MP4 in ``folder``, every frame sent (they are compared one by one): the clip as read back,
    the recording and the call's stats."""
    height, width = frames[0].shape[:2]
    clip, out, stats = folder / "clip.mp4", folder / "out.mp4", folder / "stats.json"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), fps, (width, height))
    for image in frames:
        writer.write(image)
    writer.release()
    args = ["demo", "--input", str(clip), "--output", str(out), "--no-sound", "--every-frame"]
    assert main([*args, "--stats", str(stats)]) == 0
    return read_video(clip), read_video(out), json.loads(stats.read_text())
