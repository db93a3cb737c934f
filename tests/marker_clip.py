"""The bundled clip's frames for the marker tests, with its markers painted out or recoloured
(drawn as tools/make_demo_clip.py draws them, at the truth's positions)."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import cv2
import numpy as np

from facewire.sender.capture import VideoSource, demo_clip_path

TRUTH = Path(__file__).resolve().parent.parent / "sender" / "data" / "demo_clip_truth.npz"


def truth() -> dict[str, np.ndarray]:
    return dict(np.load(TRUTH))


def clip_frames(
    limit: int | None = None, change: Callable[[int, np.ndarray], None] | None = None
) -> Iterator[tuple[int, np.ndarray]]:
    """(index, BGR frame) of the bundled clip, each changed in place by ``change`` first."""
    with VideoSource(demo_clip_path()) as video:
        for frame in video.frames(limit=limit):
            image = frame.image.copy()
            if change is not None:
                change(frame.index, image)
            yield frame.index, image


def paint_out(image: np.ndarray, xy: np.ndarray, radius: float = 7.0) -> None:
    """Cover the marker at ``xy`` (2,) px with the skin around it (the median of a ring)."""
    x, y = xy
    r = int(np.ceil(radius)) + 7
    x0, y0 = max(int(x) - r, 0), max(int(y) - r, 0)
    patch = image[y0 : int(y) + r + 1, x0 : int(x) + r + 1]
    yy, xx = np.mgrid[y0 : y0 + patch.shape[0], x0 : x0 + patch.shape[1]]
    d = np.hypot(xx - x, yy - y)
    ring = (d > radius + 2) & (d < radius + 6)
    patch[d <= radius] = np.median(patch[ring], axis=0)


def recolour(image: np.ndarray, xy: np.ndarray, colour: tuple[int, int, int]) -> None:
    """Draw a sticker of ``colour`` (BGR) over the one at ``xy``, a pixel wider."""
    centre = (int(round(xy[0] * 16)), int(round(xy[1] * 16)))
    cv2.circle(image, centre, 4 * 16, colour, -1, cv2.LINE_AA, 4)
