"""Video input: a camera index, a video file, or the bundled demo clip."""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import cv2
import numpy as np

from facewire.protocol.clock import now_us

logger = logging.getLogger(__name__)

DEMO_CLIP = "demo_clip.mp4"
#: A paced file's frame this many frames' time late is left out: V4L2 cameras queue about
#: four, so a reader this far behind would have lost frames from a camera too. Less, and a
#: call's slow first frames (its first keyframe, its first patches) cost frames on a quiet
#: machine; more, and the sound, sent with the frames, falls further behind its pace.
BEHIND_FRAMES = 3


class CaptureError(RuntimeError):
    """The source cannot be opened or read; the message is one readable line."""


@dataclass(frozen=True)
class CapturedFrame:
    """One input frame.

    index : position in the source, from 0
    image : (h, w, 3) uint8 BGR
    capture_us : time the frame was taken, on this process's monotonic clock (µs)
    """

    index: int
    image: np.ndarray
    capture_us: int


def demo_clip_path() -> Path:
    """The bundled clip (rendered from the face model, with ground truth beside it)."""
    return Path(str(resources.files("facewire.sender") / "data" / DEMO_CLIP))


class VideoSource:
    """Frames from a camera or a file.

    source : camera index (int or digit string), or a path to any video OpenCV reads.
    realtime : pace a file at its frame rate (as a camera would deliver it); False reads
        as fast as possible (for measuring). A paced frame read more than BEHIND_FRAMES
        frames' time after it was due is left out (:attr:`dropped`), as a camera's driver,
        its few buffers full, drops frames for a reader that falls behind: the call, and the
        sound sent with its frames, keep real time on a machine too busy for every frame.
    keep_late : pace a file but never leave a frame out (a test that follows a call frame by
        frame through loss and recovery).
    """

    def __init__(
        self, source: int | str | Path, realtime: bool = False, keep_late: bool = False
    ) -> None:
        camera = source if isinstance(source, int) else None
        if isinstance(source, str) and source.isdigit():
            camera = int(source)
        self.is_camera = camera is not None
        if camera is not None:
            index = camera
            self._cap = cv2.VideoCapture(index)
            if not self._cap.isOpened():
                raise CaptureError(f"cannot open camera {index}: no such device or it is busy")
            self.name = f"camera {index}"
        else:
            path = Path(str(source))
            if path.is_dir():
                raise CaptureError(f"cannot open video {path}: it is a folder, not a file")
            if not path.is_file():
                raise CaptureError(f"cannot open video {path}: no such file")
            self._cap = cv2.VideoCapture(str(path))
            if not self._cap.isOpened():
                raise CaptureError(f"cannot open video {path}: not a video OpenCV can read")
            self.name = str(path)
        ok, first = self._cap.read()
        if not ok or first is None:
            self._cap.release()
            raise CaptureError(f"cannot read a frame from {self.name}")
        self._first: np.ndarray | None = first
        self.height, self.width = first.shape[:2]
        fps = self._cap.get(cv2.CAP_PROP_FPS)
        self.fps = float(fps) if fps and 1.0 <= fps <= 240.0 else 30.0
        count = int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))
        self.frame_count = count if count > 0 and not self.is_camera else None
        self.realtime = realtime and not self.is_camera
        self.keep_late = keep_late
        self._origin_us, self._origin_index = now_us(), 0
        self.dropped = 0  # paced frames left out, read too late
        self.read_to = 0  # the number of the frame after the last one read
        logger.info("opened %s: %dx%d at %.2f fps", self.name, self.width, self.height, self.fps)

    def frames(self, limit: int | None = None) -> Iterator[CapturedFrame]:
        """Yield frames in order, at most ``limit``; stops at the end of a file."""
        self.resync()
        index = 0
        while limit is None or index < limit:
            if self._first is not None:
                image, self._first = self._first, None
            else:
                ok, image = self._cap.read()
                if not ok or image is None:
                    break
            self.read_to = index + 1
            if self.realtime:
                due = self._origin_us + int((index - self._origin_index) * 1e6 / self.fps)
                wait = due - now_us()
                if wait > 0:
                    time.sleep(wait / 1e6)
                elif -wait > BEHIND_FRAMES * 1e6 / self.fps and not self.keep_late:
                    self.dropped += 1
                    index += 1
                    continue
            yield CapturedFrame(index, image, now_us())
            index += 1

    def resync(self, next_index: int = 0) -> None:
        """Pace from now on: frame ``next_index`` is due at once (after a pause in reading)."""
        self._origin_us = now_us()
        self._origin_index = next_index

    def close(self) -> None:
        self._cap.release()

    def __enter__(self) -> VideoSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
