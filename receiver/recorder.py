"""MP4 recording of the rebuilt frames."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

logger = logging.getLogger(__name__)


class Mp4Recorder:
    """Writes BGR frames of one size to an MPEG-4 file (codec mp4v, plays everywhere)."""

    def __init__(self, path: str | Path, width: int, height: int, fps: float) -> None:
        self.path = Path(path)
        self.size = (width, height)
        if self.path.parent and not self.path.parent.exists():
            raise OSError(f"cannot write {self.path}: folder {self.path.parent} does not exist")
        self._writer = cv2.VideoWriter(
            str(self.path), cv2.VideoWriter.fourcc(*"mp4v"), fps, self.size
        )
        if not self._writer.isOpened():
            raise OSError(f"cannot write video {self.path}")
        self.frames = 0

    def write(self, image: np.ndarray) -> None:
        if image.shape[1::-1] != self.size:
            raise ValueError(f"expected a {self.size[0]}x{self.size[1]} frame, got {image.shape}")
        self._writer.write(image)
        self.frames += 1

    def close(self) -> None:
        self._writer.release()

    def __enter__(self) -> Mp4Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
