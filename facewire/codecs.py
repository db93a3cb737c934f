"""Ordinary video codecs with video-call settings, through PyAV (FFmpeg's libraries).

Each codec encodes a clip at a target bit rate and a frame size, in memory (no container),
with the settings a real-time call would use: one key frame at the start, no B-frames, no
look-ahead, a one-second rate buffer. The achieved rate is read from the bitstream (the
packets' bytes), not taken from the target. Decoding gives frame i for input frame i by the
frame number the encoder was given (its pts); a frame the encoder dropped is None, and the
quality metric holds the previous one in its place.

Colour: frames go from RGB to YUV 4:2:0 and back through libswscale, scaled (for the lower
rungs of the resolution ladder) with its bicubic filter, as FFmpeg's ``scale`` filter does by
default; the same as the ffmpeg program does with an RGB input.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from fractions import Fraction
from typing import TYPE_CHECKING, cast

import numpy as np

if TYPE_CHECKING:
    from av.video.codeccontext import VideoCodecContext

logger = logging.getLogger(__name__)

# SVT-AV1 prints its configuration on stderr for every encoder unless told otherwise
# (1: errors only); it reads this when an encoder is made.
os.environ.setdefault("SVT_LOG", "1")

#: Key-frame interval: longer than any clip measured, so a call has one key frame, at the
#: start (as ours has one snapshot). A real call sends another only when a receiver asks.
GOP_FRAMES = 100_000
#: libswscale's filter for both the ladder's down-scaling and the decoder's up-scaling.
SCALER = "BICUBIC"


@dataclass(frozen=True)
class CodecSpec:
    """One codec and its call settings (FFmpeg AVOptions, as ``ffmpeg -KEY VALUE`` takes them).

    ``options`` are fixed; :meth:`encoder_options` adds the rate ones.
    """

    name: str
    label: str
    encoder: str
    decoder: str
    options: Mapping[str, str]
    #: also set minrate = bitrate (libvpx chooses CBR when min = max = target)
    cbr_minrate: bool = False

    def encoder_options(self, bitrate: int | str) -> dict[str, str]:
        """Every AVOption given to the encoder at ``bitrate`` bit/s (a string is put in as it
        is: "RATE" describes the settings)."""
        rate = bitrate if isinstance(bitrate, str) else str(int(bitrate))
        out = dict(self.options)
        out.update(b=rate, maxrate=rate, bufsize=rate, g=str(GOP_FRAMES))
        if self.cbr_minrate:
            out["minrate"] = rate
        return out


CODECS: dict[str, CodecSpec] = {
    spec.name: spec
    for spec in (
        CodecSpec(
            "h264",
            "H.264 (x264 medium, zerolatency)",
            "libx264",
            "h264",
            # zerolatency: no B-frames, no look-ahead, no frame threads. One thread: with
            # zerolatency's sliced threads the bitstream changes from run to run (by 0.015
            # face SSIM at 16 kbit/s on carphone), and a measurement must repeat.
            {"preset": "medium", "tune": "zerolatency", "bf": "0", "threads": "1"},
        ),
        CodecSpec(
            "vp9",
            "VP9 (libvpx realtime, speed 6, CBR)",
            "libvpx-vp9",
            "vp9",
            {"deadline": "realtime", "cpu-used": "6", "lag-in-frames": "0", "row-mt": "1"},
            cbr_minrate=True,
        ),
        CodecSpec(
            "av1",
            "AV1 (SVT-AV1 preset 10, rtc, CBR)",
            "libsvtav1",
            "libdav1d",
            # rtc: the real-time tuning; pred-struct 1: low delay (no frame waits for a later
            # one); rc 2: CBR, the only rate control SVT-AV1 has for low delay.
            {"preset": "10", "svtav1-params": "rtc=1:pred-struct=1:rc=2"},
        ),
    )
}


def codec_spec(name: str) -> CodecSpec:
    """The spec named ``name``; ValueError naming the known ones otherwise."""
    try:
        return CODECS[name]
    except KeyError:
        known = ", ".join(CODECS)
        raise ValueError(f"unknown codec {name!r} (known: {known})") from None


def check_available(specs: Iterable[CodecSpec]) -> None:
    """ValueError unless PyAV's FFmpeg has every encoder and decoder named."""
    import av

    missing = [
        c for spec in specs for c in (spec.encoder, spec.decoder) if c not in av.codecs_available
    ]
    if missing:
        raise ValueError(f"this PyAV build has no {', '.join(missing)}")


def even_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """(w, h) of a ladder rung: the input scaled by ``scale``, each side rounded to even
    (4:2:0 needs even sides), at least 16."""
    return (
        max(16, 2 * round(width * scale / 2)),
        max(16, 2 * round(height * scale / 2)),
    )


@dataclass
class Encoded:
    """A clip encoded by one codec at one target rate and size.

    packets : the bitstream, one bytes per packet, in decode order
    pts : the input frame number of each packet
    """

    codec: str
    target_bps: int
    width: int
    height: int
    frames: int
    fps: float
    packets: list[bytes] = field(default_factory=list)
    pts: list[int] = field(default_factory=list)
    keyframes: int = 0

    @property
    def bytes(self) -> int:
        return sum(len(p) for p in self.packets)

    @property
    def duration_s(self) -> float:
        return self.frames / self.fps

    @property
    def bps(self) -> float:
        """Achieved bits per second over the clip, the first key frame amortised."""
        return self.bytes * 8 / self.duration_s

    @property
    def steady_bps(self) -> float:
        """Bits per second of every packet but the first (the key frame), over the clip:
        as a call's steady state is counted (after its snapshot)."""
        return (self.bytes - self.first_packet_bytes) * 8 / self.duration_s

    @property
    def first_packet_bytes(self) -> int:
        return len(self.packets[0]) if self.packets else 0


@contextmanager
def ordinary_scheduling() -> Iterator[None]:
    """Undo what an encoder does to the calling thread's scheduling.

    Run as root, SVT-AV1 makes the thread that opens it real-time (SCHED_FIFO 99). Every
    process started from that thread afterwards inherits it, and a real-time process whose
    BLAS waits for its own worker threads on two cores never lets them run: the loopback call
    that follows hung in an SVD for good.
    """
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        yield
    finally:
        if (os.sched_getscheduler(0), os.sched_getparam(0)) != (policy, param):
            os.sched_setscheduler(0, policy, param)


def _frame_rate(fps: float) -> Fraction:
    return Fraction(fps).limit_denominator(1001)


@ordinary_scheduling()
def encode(
    frames: Iterable[np.ndarray],
    spec: CodecSpec,
    bitrate: int,
    size: tuple[int, int],
    fps: float,
) -> Encoded:
    """Encode BGR frames ((h, w, 3) uint8) at ``size`` (w, h) and ``bitrate`` bit/s."""
    import av

    width, height = size
    rate = _frame_rate(fps)
    ctx = cast("VideoCodecContext", av.CodecContext.create(spec.encoder, "w"))
    ctx.width, ctx.height = width, height
    ctx.pix_fmt = "yuv420p"
    ctx.time_base = 1 / rate
    ctx.framerate = rate
    ctx.bit_rate = int(bitrate)
    ctx.options = spec.encoder_options(bitrate)
    try:
        ctx.open()
    except av.FFmpegError as exc:
        msg = f"{spec.encoder} refused {width}x{height} at {bitrate} bit/s: {exc}"
        raise RuntimeError(msg) from None
    out = Encoded(spec.name, int(bitrate), width, height, 0, fps)

    def take(packets: list[av.Packet]) -> None:
        for p in packets:
            out.packets.append(bytes(p))
            out.pts.append(int(p.pts) if p.pts is not None else -1)
            out.keyframes += bool(p.is_keyframe)

    for i, image in enumerate(frames):
        # As RGB: libswscale has a fast BGR24 -> YUV 4:2:0 path of its own whose rounding
        # differs from the one every other RGB input (the ffmpeg program's included) takes.
        rgb = np.ascontiguousarray(image[..., ::-1])
        frame = av.VideoFrame.from_ndarray(rgb, format="rgb24")
        frame = frame.reformat(width, height, "yuv420p", interpolation=SCALER)
        frame.pts = i
        take(ctx.encode(frame))
        out.frames += 1
    take(ctx.encode(None))
    if out.frames == 0:
        raise ValueError("no frames to encode")
    return out


def decode(encoded: Encoded, spec: CodecSpec, size: tuple[int, int]) -> Iterator[np.ndarray | None]:
    """BGR frames ((h, w, 3) uint8 at ``size`` (w, h)) for input frames 0 .. n-1 in order;
    None for a frame the encoder dropped (no packet carried it)."""
    import av

    width, height = size
    ctx = cast("VideoCodecContext", av.CodecContext.create(spec.decoder, "r"))
    rate = _frame_rate(encoded.fps)
    nxt = 0

    def pictures() -> Iterator[av.VideoFrame]:
        for data, pts in zip(encoded.packets, encoded.pts, strict=True):
            packet = av.Packet(data)
            packet.pts = packet.dts = pts
            packet.time_base = 1 / rate
            yield from ctx.decode(packet)
        yield from ctx.decode(None)

    for picture in pictures():
        index = picture.pts
        if index is None or index < nxt:
            raise RuntimeError(f"{spec.decoder} gave frame {index} after frame {nxt - 1}")
        while nxt < index:  # frames the encoder dropped
            yield None
            nxt += 1
        if index >= encoded.frames:
            break
        rgb = picture.reformat(width, height, "rgb24", interpolation=SCALER).to_ndarray()
        yield np.ascontiguousarray(rgb[..., ::-1])
        nxt += 1
    while nxt < encoded.frames:
        yield None
        nxt += 1
