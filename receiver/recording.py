"""The receiver's MP4 recording, encoded on its own thread.

Encoding a frame costs about 2 ms at 640x480 and 5 ms at 1280x720 (50 ms at 3840x2160), and
a frame that arrives after a gap is written several times (the held picture, so frame i stays
frame i). On the receive loop's thread that time adds to every later frame's latency; on a
thread of its own (OpenCV's colour conversion and PyAV's encoder let go of the GIL) it
overlaps the next render.
"""

from __future__ import annotations

import logging
import queue
import threading
from pathlib import Path

import numpy as np

from facewire.receiver.recorder import Mp4Recorder

logger = logging.getLogger(__name__)

#: Pictures waiting to be encoded, in bytes at most (at least 4 pictures): bounded memory; a
#: writer that falls further behind holds the receive loop up rather than drop frames, since
#: the recording must stay aligned with the sender's frames.
MAX_QUEUED_BYTES = 100_000_000


class BackgroundRecorder:
    """An :class:`Mp4Recorder` fed through a bounded queue and written by a thread.

    ``write`` takes the picture as it is: the caller must not change it afterwards (pass a
    copy of a buffer that will be reused). ``close`` writes what is queued, then the index.
    """

    def __init__(self, path: str | Path, width: int, height: int, fps: float) -> None:
        self._recorder = Mp4Recorder(path, width, height, fps)
        self.path = self._recorder.path
        self.size = self._recorder.size
        depth = max(4, MAX_QUEUED_BYTES // (width * height * 3))
        self._queue: queue.Queue[np.ndarray | None] = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="mp4-recorder", daemon=True)
        self._thread.start()
        self._closed = False
        self.frames = 0

    def write(self, image: np.ndarray) -> None:
        if self._error is not None:
            raise OSError(f"recording {self.path} failed: {self._error}")
        if image.shape[1::-1] != self.size:
            raise ValueError(f"expected a {self.size[0]}x{self.size[1]} frame, got {image.shape}")
        self._queue.put(image)
        self.frames += 1

    def _run(self) -> None:
        while True:
            image = self._queue.get()
            if image is None:
                return
            if self._error is not None:
                continue  # keep draining so write() never blocks on a dead writer
            try:
                self._recorder.write(image)
            except Exception as exc:  # reported by the next write() or close()
                logger.debug("recording failed", exc_info=True)
                self._error = exc

    def close(self) -> None:
        """Write the queued pictures and the file's index (the MP4 is playable after it)."""
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        self._thread.join()
        self._recorder.close()
        if self._error is not None:
            raise OSError(f"recording {self.path} failed: {self._error}")

    def __enter__(self) -> BackgroundRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
