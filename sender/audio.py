"""The sender's sound: capture (a file's audio track or a microphone), Opus, AudioFrame packets.

Sound is Opus at 48 kHz mono in 20, 40 or 60 ms packets (docs/protocol.md, AudioFrame: the
longer ones where the budget is thin, :func:`frame_ms_for`), coded through
PyAV's libopus for speech: about 12 kbit/s, in-band FEC (each packet also carries a coarse
copy of the one before), tuned for the loss expected. PyAV's libopus wrapper has no DTX
switch, so the sender does it: once the input has been silent for a moment, frames are
encoded (the coder's state runs on) but not sent; the receiver conceals a gap as it would a
loss, which Opus makes fade to silence.

Audio frames are stamped on the video's clock: a file's sound is sent as its video frames
are read, sample s of the file captured at ``capture_us`` of the video frame at that point
plus the time between them. So lips and voice stay together however the video was paced.
A microphone's frames are stamped when the sound card says they were captured.
"""

from __future__ import annotations

import fractions
import logging
import math
import queue
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from facewire.protocol.clock import now_us
from facewire.protocol.constants import AUDIO_FRAME_MS, AUDIO_FRAME_SAMPLES, AUDIO_RATE
from facewire.protocol.packets import AudioFrame
from facewire.sender.capture import CapturedFrame

logger = logging.getLogger(__name__)

#: Beside the bundled clip (which has no audio track): its speech (tools/make_demo_speech.py).
DEMO_SPEECH = "demo_clip_speech.wav"
#: Frames quieter than this (RMS, dB below full scale) count as silence for DTX.
SILENCE_DBFS = -55.0
#: Silent frames still sent after sound, so the voice's tail and the fade are not cut.
DTX_HANGOVER_FRAMES = 10
#: Bit rates accepted, bit/s (Opus's own range is 6 to 510 kbit/s).
MIN_BITRATE, MAX_BITRATE = 6_000, 128_000
#: Opus packet lengths, ms, and the budgets (bit/s, on the wire) at or under which the longer
#: ones are used: each packet costs its AudioFrame header (13 bytes) and a place in a
#: datagram, 5.6 kbit/s at 20 ms, 1.9 at 60; a longer packet waits longer to fill (40 ms more
#: at 60 ms), so the sound comes later behind the lips: only where the bits matter more.
FRAME_MS = (20, 40, 60)
LONGER_FRAMES_AT_BPS = {40: 24_000.0, 60: 16_000.0}


def frame_ms_for(budget_bps: float) -> int:
    """The Opus packet length for a call with this on-the-wire budget."""
    if budget_bps <= LONGER_FRAMES_AT_BPS[60]:
        return 60
    if budget_bps <= LONGER_FRAMES_AT_BPS[40]:
        return 40
    return 20


class AudioError(RuntimeError):
    """Sound cannot be captured or coded; the message is one readable line."""


@dataclass(frozen=True)
class AudioSettings:
    """How the sender codes its sound.

    bitrate : Opus bit rate, bit/s
    fec : in-band forward error correction
    expected_loss : percent of packets the link is expected to lose (sizes the FEC)
    dtx : leave silent frames out
    frame_ms : each packet's length, 20, 40 or 60 ms
    """

    bitrate: int = 12_000
    fec: bool = True
    expected_loss: int = 5
    dtx: bool = True
    frame_ms: int = 20

    def __post_init__(self) -> None:
        if not MIN_BITRATE <= self.bitrate <= MAX_BITRATE:
            raise AudioError(
                f"audio bit rate {self.bitrate} bit/s outside [{MIN_BITRATE}, {MAX_BITRATE}]"
            )
        if not 0 <= self.expected_loss <= 100:
            raise AudioError(f"expected loss {self.expected_loss}% outside [0, 100]")
        if self.frame_ms not in FRAME_MS:
            raise AudioError(f"Opus packets of {self.frame_ms} ms: expected one of {FRAME_MS}")


@dataclass(frozen=True)
class CodedFrame:
    """One Opus packet: ``seq`` (20 ms steps: a longer packet covers the steps from it on),
    its first decoded sample's input position (``sample``, 48 kHz samples; the coder's
    look-ahead makes the first one negative)."""

    seq: int
    sample: int
    data: bytes
    silent: bool


class OpusEncoder:
    """Opus through PyAV, 20 ms frames of 48 kHz mono int16 in, packets of
    ``settings.frame_ms`` out in order (PyAV gathers the input into them)."""

    def __init__(self, settings: AudioSettings) -> None:
        import av

        self.settings = settings
        try:
            ctx: Any = av.CodecContext.create("libopus", "w")
        except Exception as exc:  # an FFmpeg build without libopus
            raise AudioError(f"no Opus encoder in this PyAV build: {exc}") from None
        ctx.sample_rate = AUDIO_RATE
        ctx.layout = "mono"
        ctx.format = "s16"
        ctx.bit_rate = settings.bitrate
        ctx.time_base = fractions.Fraction(1, AUDIO_RATE)
        ctx.options = {
            "application": "voip",
            "frame_duration": str(settings.frame_ms),
            "fec": "1" if settings.fec else "0",
            "packet_loss": str(settings.expected_loss),
            "vbr": "on",
        }
        ctx.open()
        self._ctx = ctx
        self._steps = settings.frame_ms // AUDIO_FRAME_MS
        self._frame = av.AudioFrame
        self._pts = 0
        self._silent = 0  # silent frames in a row (input side)
        self._silence: list[bool] = []  # per input frame still inside the coder

    def encode(self, pcm: np.ndarray) -> list[CodedFrame]:
        """One 20 ms frame (AUDIO_FRAME_SAMPLES int16) in; the packets that came out."""
        if pcm.shape != (AUDIO_FRAME_SAMPLES,):
            raise ValueError(f"expected ({AUDIO_FRAME_SAMPLES},) samples, got {pcm.shape}")
        rms = math.sqrt(float(np.mean(np.square(pcm, dtype=np.float64)))) / 32768.0
        quiet = rms < 10 ** (SILENCE_DBFS / 20)
        self._silent = self._silent + 1 if quiet else 0
        self._silence.append(self._silent > DTX_HANGOVER_FRAMES)
        frame = self._frame.from_ndarray(pcm.reshape(1, -1), format="s16", layout="mono")
        frame.sample_rate = AUDIO_RATE
        frame.pts = self._pts
        self._pts += AUDIO_FRAME_SAMPLES
        return self._take(self._ctx.encode(frame))

    def flush(self) -> list[CodedFrame]:
        return self._take(self._ctx.encode(None))

    def _take(self, packets: Iterable[Any]) -> list[CodedFrame]:
        out = []
        for packet in packets:
            sample = int(packet.pts)
            # Packet k decodes to input [k * 960 - d, ...), d the coder's look-ahead (312).
            seq = round(sample / AUDIO_FRAME_SAMPLES)
            # The packet decodes to input [sample, sample + steps * 960): silent when the
            # input frames it spans were all silent.
            idx = max(0, sample // AUDIO_FRAME_SAMPLES)
            spans = self._steps + 1
            silent = all(self._silence[idx : idx + spans]) if self._silence[idx:] else False
            out.append(CodedFrame(seq, sample, bytes(packet), silent))
        return out


class AudioTrack(Protocol):
    """48 kHz mono int16 sound read in order."""

    name: str

    def read(self, count: int) -> np.ndarray | None:
        """The next ``count`` samples (fewer at the end), or None at the end."""


class FileTrack:
    """A file's first audio track, decoded with PyAV and resampled to 48 kHz mono.

    Any rate and channel layout (5.1 is mixed down). Raises AudioError (one line) when the
    file cannot be opened; :func:`open_track` returns None when it has no audio track.
    """

    def __init__(self, path: str | Path) -> None:
        import av

        self.name = str(path)
        try:
            self._container: Any = av.open(str(path))
        except (OSError, av.FFmpegError) as exc:
            raise AudioError(f"cannot read sound from {path}: {exc}") from None
        streams = self._container.streams.audio
        if not streams:
            self._container.close()
            raise LookupError(f"{path} has no audio track")
        self.stream = streams[0]
        self._resampler = av.AudioResampler(format="s16", layout="mono", rate=AUDIO_RATE)
        self._frames = self._container.decode(self.stream)
        self._buffer = np.zeros(0, np.int16)
        self._done = False
        logger.info(
            "sound from %s: %s, %d Hz, %d channels",
            path,
            self.stream.codec_context.name,
            self.stream.codec_context.sample_rate,
            self.stream.codec_context.channels,
        )

    def read(self, count: int) -> np.ndarray | None:
        while len(self._buffer) < count and not self._done:
            try:
                frame = next(self._frames)
            except StopIteration:
                self._done = True
                frame = None
            except Exception as exc:  # a damaged stream: end the sound, keep the call
                logger.warning("sound from %s ends early: %s", self.name, exc)
                self._done = True
                frame = None
            frame_out = self._resampler.resample(frame)
            chunks = [f.to_ndarray().reshape(-1) for f in frame_out]
            if chunks:
                self._buffer = np.concatenate([self._buffer, *chunks])
        if not len(self._buffer) and self._done:
            return None
        out, self._buffer = self._buffer[:count], self._buffer[count:]
        return out

    def close(self) -> None:
        self._container.close()


class LoopedTrack:
    """A file's sound again and again, as ``send --loop`` plays its pictures."""

    def __init__(self, path: str | Path) -> None:
        self.name = str(path)
        self._path = path
        self._track = FileTrack(path)

    def read(self, count: int) -> np.ndarray | None:
        pcm = self._track.read(count)
        if pcm is None:
            self._track = FileTrack(self._path)
            pcm = self._track.read(count)
        return pcm


def open_track(path: str | Path) -> FileTrack | None:
    """The audio track of ``path``, or None (logged) when it has none."""
    try:
        return FileTrack(path)
    except LookupError as exc:
        logger.info("%s", exc)
        return None


def demo_speech_path() -> Path:
    from importlib import resources

    return Path(str(resources.files("facewire.sender") / "data" / DEMO_SPEECH))


class AudioSender:
    """Codes ``track`` and publishes it as AudioFrame packets, in step with the video.

    :meth:`send_until` is called with each video frame: it sends every 20 ms frame of the
    file's sound up to that frame's place in the file, stamped on the video's clock.
    """

    def __init__(
        self,
        track: AudioTrack,
        publish: Callable[[AudioFrame], None],
        settings: AudioSettings | None = None,
    ) -> None:
        self.track = track
        self.settings = settings or AudioSettings()
        self._encoder = OpusEncoder(self.settings)
        self._publish = publish
        self._read = 0  # samples read from the track
        self._ended = False
        self.packets = 0
        self.bytes = 0
        self.frames_dtx = 0  # coded but left out: silence

    def send_until(self, media_s: float, anchor_media_s: float, anchor_us: int) -> None:
        """Send the sound before ``media_s`` (seconds into the file); the video frame at
        ``anchor_media_s`` was captured at ``anchor_us``."""
        target = int(media_s * AUDIO_RATE)
        while not self._ended and self._read + AUDIO_FRAME_SAMPLES <= target:
            pcm = self.track.read(AUDIO_FRAME_SAMPLES)
            if pcm is None:
                self._ended = True
                coded = self._encoder.flush()
            else:
                if len(pcm) < AUDIO_FRAME_SAMPLES:
                    pcm = np.pad(pcm, (0, AUDIO_FRAME_SAMPLES - len(pcm)))
                self._read += AUDIO_FRAME_SAMPLES
                coded = self._encoder.encode(pcm)
            for frame in coded:
                capture_us = anchor_us + round((frame.sample / AUDIO_RATE - anchor_media_s) * 1e6)
                self._send(frame, capture_us)

    def _send(self, frame: CodedFrame, capture_us: int) -> None:
        if frame.seq < 0:
            return
        if self.settings.dtx and frame.silent:
            self.frames_dtx += 1
            return
        packet = AudioFrame(frame.seq, capture_us, frame.data)
        self._publish(packet)
        self.packets += 1
        self.bytes += len(frame.data)


def with_sound(
    frames: Iterable[CapturedFrame], sound: AudioSender | None, fps: float
) -> Iterator[CapturedFrame]:
    """``frames`` as they are; before each, the file's sound up to that frame is sent.

    Sound is sent only as far as the frame's own instant (what a microphone would have
    captured by then), stamped against that frame's capture time.
    """
    for frame in frames:
        if sound is not None:
            start = getattr(sound.track, "start_us", None)
            if start is None:  # a file: its place is the frame's
                media_s = frame.index / fps
                sound.send_until(media_s, media_s, frame.capture_us)
            else:  # a microphone: what it has captured by the frame's capture time
                sound.send_until((frame.capture_us - start) / 1e6, 0.0, start)
        yield frame


class MicrophoneTrack:
    """The default input device through sounddevice (PortAudio), 48 kHz mono.

    Raises AudioError (one line) when sounddevice is not installed or there is no input
    device. Samples are stamped with the clock of the video (:func:`facewire.protocol.clock.now_us`)
    when the callback delivers them, less their own duration.
    """

    def __init__(self) -> None:
        try:
            import sounddevice as sd
        except (ImportError, OSError) as exc:
            raise AudioError(f"no sound device: {exc}") from None
        self.name = "microphone"
        self._queue: queue.Queue[tuple[int, np.ndarray]] = queue.Queue(maxsize=500)
        self._buffer = np.zeros(0, np.int16)

        def callback(indata: np.ndarray, frames: int, time: Any, status: Any) -> None:
            stamp = now_us() - round(frames / AUDIO_RATE * 1e6)
            try:
                self._queue.put_nowait((stamp, indata[:, 0].copy()))
            except queue.Full:
                pass

        try:
            self._stream = sd.InputStream(
                samplerate=AUDIO_RATE,
                channels=1,
                dtype="int16",
                blocksize=AUDIO_FRAME_SAMPLES,
                callback=callback,
            )
            self.start_us = now_us()
            self._stream.start()
        except Exception as exc:  # PortAudioError: no device, busy, unsupported rate
            raise AudioError(f"no sound device: {exc}") from None

    def read(self, count: int) -> np.ndarray | None:
        while len(self._buffer) < count:
            try:
                _, block = self._queue.get(timeout=1.0)
            except queue.Empty:
                return None
            self._buffer = np.concatenate([self._buffer, block])
        out, self._buffer = self._buffer[:count], self._buffer[count:]
        return out

    def close(self) -> None:
        self._stream.close()


def sound_for(
    source: int | str | Path,
    is_camera: bool,
    realtime: bool,
    publish: Callable[[AudioFrame], None],
    settings: AudioSettings | None = None,
    notify: Callable[[str], None] = logger.info,
    loop: bool = False,
) -> AudioSender | None:
    """The sound to send with a video ``source``, or None with one line to ``notify`` why.

    A camera's sound is the default microphone's; a file's, its first audio track (the
    bundled clip's speech lies beside it), again and again with ``loop``. A file read faster
    than its frame rate has no clock to play sound on: it is sent without.
    """
    track: AudioTrack | None
    try:
        if is_camera:
            track = MicrophoneTrack()
        elif not realtime:
            notify("no sound: the file is read faster than its frame rate")
            return None
        else:
            path = Path(str(source))
            track = open_track(path)
            if track is None and path.name == "demo_clip.mp4":
                path = demo_speech_path()
                track = open_track(path)
            if track is None:
                notify(f"{source} has no audio track: the call goes on without sound")
                return None
            if loop:
                track = LoopedTrack(path)
        return AudioSender(track, publish, settings)
    except AudioError as exc:
        notify(f"{exc}: the call goes on without sound")
        return None
