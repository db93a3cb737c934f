"""MP4 recording of the rebuilt frames."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

logger = logging.getLogger(__name__)


def padded_size(width: int, height: int) -> tuple[int, int]:
    """The size a recording of width x height frames has: MPEG-4 needs even sides."""
    return width + width % 2, height + height % 2


def crop_to(frame: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A recorded frame cut back to the (h, w) of the frames that were recorded."""
    return frame[: shape[0], : shape[1]]


class Mp4Recorder:
    """Writes BGR frames of one size to an MPEG-4 file (codec mp4v, plays everywhere).

    An odd width or height is recorded one pixel larger, the last column or row repeated
    (OpenCV's writer would otherwise drop it silently); :func:`crop_to` cuts it back.
    """

    def __init__(self, path: str | Path, width: int, height: int, fps: float) -> None:
        self.path = Path(path)
        self.size = (width, height)
        self._pad = (padded_size(width, height)[0] - width, padded_size(width, height)[1] - height)
        if self.path.parent and not self.path.parent.exists():
            raise OSError(f"cannot write {self.path}: folder {self.path.parent} does not exist")
        self._writer = cv2.VideoWriter(
            str(self.path), cv2.VideoWriter.fourcc(*"mp4v"), fps, padded_size(width, height)
        )
        if not self._writer.isOpened():
            raise OSError(f"cannot write video {self.path}")
        self.frames = 0

    def write(self, image: np.ndarray) -> None:
        if image.shape[1::-1] != self.size:
            raise ValueError(f"expected a {self.size[0]}x{self.size[1]} frame, got {image.shape}")
        if any(self._pad):
            image = cv2.copyMakeBorder(
                image, 0, self._pad[1], 0, self._pad[0], cv2.BORDER_REPLICATE
            )
        self._writer.write(image)
        self.frames += 1

    def close(self) -> None:
        self._writer.release()

    def __enter__(self) -> Mp4Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
