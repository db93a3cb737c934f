"""MP4 recording of the rebuilt frames."""

from __future__ import annotations

import logging
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

logger = logging.getLogger(__name__)

#: MPEG-4's quantiser scale (1 best .. 31): at 2 carphone's rebuilt face scores 0.7694 SSIM
#: recorded against 0.7717 unrecorded; OpenCV's writer (its default rate) scored 0.7639.
QSCALE = 2
#: Frames of at most this many pixels (176x144 up to 320x240) are recorded as H.264 at
#: H264_CRF instead: on a 40-60 px face MPEG-4's 8x8 blocks cost 0.001-0.003 face SSIM, which
#: H.264 (4x4 transforms, deblocking) mostly keeps, for 0.3 ms a frame. From CIF up MPEG-4
#: scored as well or better, in a quarter of the time (docs/what-we-tried.md, "The
#: recording").
SMALL_PIXELS = 100_000
H264_CRF = 9


def padded_size(width: int, height: int) -> tuple[int, int]:
    """The size a recording of width x height frames has: 4:2:0 needs even sides."""
    return width + width % 2, height + height % 2


def crop_to(frame: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A recorded frame cut back to the (h, w) of the frames that were recorded."""
    return frame[: shape[0], : shape[1]]


def at_input_size(frame: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A recorded frame beside its input of ``shape`` (h, w, ...): cut back, or scaled up
    to it when the call ran smaller (``--max-size``)."""
    cut = crop_to(frame, shape)
    if cut.shape[:2] == tuple(shape[:2]):
        return cut
    return cv2.resize(cut, (shape[1], shape[0]), interpolation=cv2.INTER_LINEAR)


class Mp4Recorder:
    """Writes BGR frames of one size to an MP4 file: MPEG-4 Part 2 through PyAV (4:2:0), which
    plays everywhere and encodes a 640x480 frame in about 2 ms on one thread; a small frame
    (:data:`SMALL_PIXELS`) as H.264 (libx264, veryfast, CRF :data:`H264_CRF`).

    At a fixed, fine quantiser (:data:`QSCALE`): the recording is what a user keeps and what
    the benchmarks score. OpenCV's writer at its default rate cost carphone's rebuilt face
    0.008 SSIM, this 0.002, in a file 1.3 times as large at 640x480. H.264 (libx264, veryfast,
    CRF 12) did a little better (0.0015) in smaller files, but took 4 ms a frame at 640x480
    and 12 at 1280x720, which held large calls up (docs/what-we-tried.md, "The recording").

    An odd width or height is recorded one pixel larger, the last column or row repeated
    (4:2:0 needs even sides); :func:`crop_to` cuts it back.
    """

    def __init__(self, path: str | Path, width: int, height: int, fps: float) -> None:
        import av

        self.path = Path(path)
        self.size = (width, height)
        padded = padded_size(width, height)
        self._pad = (padded[0] - width, padded[1] - height)
        if self.path.parent and not self.path.parent.exists():
            raise OSError(f"cannot write {self.path}: folder {self.path.parent} does not exist")
        try:
            self._container: av.container.OutputContainer | None = av.open(
                str(self.path), "w", format="mp4"
            )
        except (OSError, av.FFmpegError) as exc:
            raise OSError(f"cannot write video {self.path}: {exc}") from None
        rate = Fraction(fps).limit_denominator(1001)
        small = padded[0] * padded[1] <= SMALL_PIXELS
        self._stream = self._container.add_stream("libx264" if small else "mpeg4", rate=rate)
        self._stream.width, self._stream.height = padded
        self._stream.pix_fmt = "yuv420p"
        # A fixed quality, not a bit rate: every frame as fine as H264_CRF or QSCALE.
        if small:
            self._stream.options = {"preset": "veryfast", "crf": str(H264_CRF)}
        else:
            self._stream.codec_context.qscale = True
            self._stream.options = {"qmin": str(QSCALE), "qmax": str(QSCALE)}
        # One thread: the recording runs on a thread of its own beside the renderer.
        self._stream.thread_count = 1
        self.frames = 0

    def write(self, image: np.ndarray) -> None:
        if image.shape[1::-1] != self.size:
            raise ValueError(f"expected a {self.size[0]}x{self.size[1]} frame, got {image.shape}")
        if any(self._pad):
            image = cv2.copyMakeBorder(
                image, 0, self._pad[1], 0, self._pad[0], cv2.BORDER_REPLICATE
            )
        import av

        # Converted by OpenCV, which lets go of the GIL (PyAV's own conversion holds it: at
        # 3840x2160 that held the receive loop up by tens of milliseconds a frame).
        yuv = np.asarray(cv2.cvtColor(image, cv2.COLOR_BGR2YUV_I420), dtype=np.uint8)
        frame = av.VideoFrame.from_ndarray(yuv, format="yuv420p")
        frame.pts = self.frames
        if self._container is None:
            raise ValueError(f"recording {self.path} is closed")
        for packet in self._stream.encode(frame):
            self._container.mux(packet)
        self.frames += 1

    def close(self) -> None:
        """Write what the encoder still holds and the file's index (once)."""
        if self._container is None:
            return
        container, self._container = self._container, None
        try:
            for packet in self._stream.encode(None):
                container.mux(packet)
        finally:
            container.close()

    def __enter__(self) -> Mp4Recorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
