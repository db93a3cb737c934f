"""A room's gallery: every peer's picture in a grid, each with its name, served by the
two-party live view (receiver/live_view.py) as its one picture.

The receiving loop hands each peer's rendered picture to :meth:`Gallery.show`; it is due on
screen at its capture time plus the delay its peer's sound is heard with then (the sound waits
in a jitter buffer, 140 ms at least, and catches up or falls back as it plays; a picture drawn
when decoded came before its voice). The gallery holds it until then (:meth:`Gallery.tick`,
which the loop calls when :meth:`Gallery.wait_s` says), so each face is seen with its voice.
The grid is drawn at most GALLERY_FPS times a second, the senders' frame rate: a picture is
on screen within a frame of its time.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from facewire.protocol.clock import now_us

#: One tile's size (the grid's pictures are scaled to it, aspect kept).
TILE = (320, 240)
GALLERY_FPS = 30.0
#: Pictures of one peer held for their time at most (3 s at 30 fps: the sound's delay is
#: seconds at most); beyond, the oldest is dropped unseen.
MAX_HELD = 90
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


def _scaled(image: np.ndarray) -> np.ndarray:
    """``image`` scaled to fit a tile, its aspect kept."""
    w, h = TILE
    scale = min(w / image.shape[1], h / image.shape[0])
    size = (max(1, round(image.shape[1] * scale)), max(1, round(image.shape[0] * scale)))
    if size == (image.shape[1], image.shape[0]):
        return image
    return cv2.resize(image, size, interpolation=cv2.INTER_AREA)


def _tile(image: np.ndarray | None, name: str) -> np.ndarray:
    w, h = TILE
    tile = np.zeros((h, w, 3), np.uint8)
    if image is not None:
        small = _scaled(image)
        y, x = (h - small.shape[0]) // 2, (w - small.shape[1]) // 2
        tile[y : y + small.shape[0], x : x + small.shape[1]] = small
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


def _no_delay() -> int | None:
    return None


class Gallery:
    """Feeds ``sink`` (a LiveView) with the grid of the peers' pictures, each at its time
    (``clock``: µs, the monotonic clock the receiver stamps with)."""

    def __init__(self, sink: object, clock: Callable[[], int] = now_us) -> None:
        self.sink = sink
        self.clock = clock
        #: Each peer's picture on screen, scaled to its tile (None: none yet).
        self.pictures: dict[str, np.ndarray | None] = {}
        #: The capture time (µs) of the picture each peer's tile shows.
        self.captured: dict[str, int] = {}
        self.report = _Report()
        # Each peer's pictures waiting for their time, (capture µs, scaled picture), and the
        # delay after capture its sound is heard with now (µs; None: shown at once).
        self._held: dict[str, deque[tuple[int, np.ndarray]]] = {}
        self._delay: dict[str, Callable[[], int | None]] = {}
        self._drawn = -math.inf  # µs
        self._owed = False  # a picture came to the screen since the last draw
        self._latency_ms = 0.0  # capture to screen of the last picture put there
        self._seq = 0

    def joined(self, name: str, delay_us: Callable[[], int | None] = _no_delay) -> None:
        """``name``'s tile, empty until its first picture; ``delay_us()`` says how long after
        its capture a picture of it is due on screen (its sound's delay, which the sound's
        playout changes as it goes: a picture waits for the delay of when it is shown)."""
        self.pictures.setdefault(name, None)
        self._delay[name] = delay_us
        self._draw(self.clock())

    def show(self, name: str, picture: np.ndarray, capture_us: int) -> None:
        """``picture``, captured at ``capture_us``, goes on screen at its time."""
        held = self._held.setdefault(name, deque(maxlen=MAX_HELD))
        held.append((capture_us, _scaled(picture)))
        self.tick()

    def _due(self, name: str, capture_us: int) -> int:
        delay = self._delay.get(name, _no_delay)()
        return capture_us + (delay or 0)

    def wait_s(self) -> float:
        """Seconds until :meth:`tick` has something to do (a picture's time, or a draw that
        waits for the frame rate); inf when nothing waits."""
        now = self.clock()
        due = [self._due(name, held[0][0]) for name, held in self._held.items() if held]
        if self._owed:
            due.append(round(self._drawn + 1e6 / GALLERY_FPS))
        return max(0.0, (min(due) - now) / 1e6) if due else math.inf

    def tick(self) -> None:
        """Put on screen each peer's newest picture whose time has come, and draw the grid if
        that changed it and the frame rate allows."""
        now = self.clock()
        for name, held in self._held.items():
            delay = self._delay.get(name, _no_delay)() or 0
            while held and held[0][0] + delay <= now:
                self.captured[name], self.pictures[name] = held.popleft()
                self._latency_ms = (now - self.captured[name]) / 1000.0
                self._owed = True
        if self._owed and now - self._drawn >= 1e6 / GALLERY_FPS:
            self._draw(now)

    def left(self, name: str) -> None:
        self.pictures.pop(name, None)
        self.captured.pop(name, None)
        self._held.pop(name, None)
        self._delay.pop(name, None)
        self._draw(self.clock())

    def _draw(self, now: int) -> None:
        self._drawn = now
        self._owed = False
        self._seq += 1
        self.report.frames_out = self._seq
        frame = _Frame(0, self._seq, grid(self.pictures), 0, self._latency_ms)
        self.sink(frame, self.report)  # type: ignore[operator]
