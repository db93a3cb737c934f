"""A room's gallery: every peer's newest picture in a grid, each with its name, served by the
two-party live view (receiver/live_view.py) as its one picture.

The receiving loop hands each peer's rendered picture to :meth:`Gallery.show`; the grid is
drawn at most GALLERY_FPS times a second (drawing is the loop's time, and the page streams at
that rate anyway).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import cv2
import numpy as np

#: One tile's size (the grid's pictures are scaled to it, aspect kept).
TILE = (320, 240)
GALLERY_FPS = 10.0
_FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass
class _Frame:
    """What the live view reads of a picture (receiver.session.RenderedFrame's fields)."""

    session_id: int
    seq: int
    image: np.ndarray
    capture_us: int
    latency_ms: float


@dataclass
class _Report:
    """What the live view reads of the receiver's figures."""

    bytes_received: dict[str, int] = field(default_factory=dict)
    frames_out: int = 0


def _tile(image: np.ndarray | None, name: str) -> np.ndarray:
    w, h = TILE
    tile = np.zeros((h, w, 3), np.uint8)
    if image is not None:
        scale = min(w / image.shape[1], h / image.shape[0])
        size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
        small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
        y, x = (h - size[1]) // 2, (w - size[0]) // 2
        tile[y : y + size[1], x : x + size[0]] = small
    cv2.rectangle(tile, (0, h - 26), (w, h), (0, 0, 0), -1)
    cv2.putText(tile, name, (8, h - 8), _FONT, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return tile


def grid(pictures: dict[str, np.ndarray | None]) -> np.ndarray:
    """(h, w, 3) uint8: the tiles of ``pictures`` (name -> picture or None), sorted by name,
    in the squarest grid that holds them; an empty room is one tile saying so."""
    if not pictures:
        return _tile(None, "no one else here yet")
    names = sorted(pictures)
    cols = math.ceil(math.sqrt(len(names)))
    rows = math.ceil(len(names) / cols)
    w, h = TILE
    out = np.zeros((rows * h, cols * w, 3), np.uint8)
    for i, name in enumerate(names):
        r, c = divmod(i, cols)
        out[r * h : (r + 1) * h, c * w : (c + 1) * w] = _tile(pictures[name], name)
    return out


class Gallery:
    """Feeds ``sink`` (a LiveView) with the grid of the peers' newest pictures."""

    def __init__(self, sink: object) -> None:
        self.sink = sink
        self.pictures: dict[str, np.ndarray | None] = {}
        self.report = _Report()
        self._drawn = 0.0
        self._seq = 0
        self._latency_ms = 0.0

    def show(self, name: str, picture: np.ndarray, latency_ms: float, nbytes: int) -> None:
        self.pictures[name] = picture
        self.report.bytes_received["room"] = self.report.bytes_received.get("room", 0) + nbytes
        self._latency_ms = latency_ms
        self._draw(force=False)

    def joined(self, name: str) -> None:
        self.pictures.setdefault(name, None)
        self._draw(force=True)

    def left(self, name: str) -> None:
        self.pictures.pop(name, None)
        self._draw(force=True)

    def _draw(self, force: bool) -> None:
        now = time.monotonic()
        if not force and now - self._drawn < 1.0 / GALLERY_FPS:
            return
        self._drawn = now
        self._seq += 1
        self.report.frames_out = self._seq
        frame = _Frame(0, self._seq, grid(self.pictures), 0, self._latency_ms)
        self.sink(frame, self.report)  # type: ignore[operator]
