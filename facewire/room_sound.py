"""The room's sound: every peer's voice, each on its own playout, mixed into one device.

Each peer gets the two-party receiver's :class:`CallSound` (its own Opus decoder, jitter
buffer, concealment and lip sync, receiver/audio.py). What a peer's playout plays goes to a
:class:`MixerInput`, a queue of that peer's 20 ms steps; the sound device's callback sums the
head of every queue (:meth:`Mixer.fill`). Without a device each peer plays into a null sink,
timed the same way, and its voice is only recorded, into that peer's MP4.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from facewire.protocol.constants import AUDIO_FRAME_MS, AUDIO_FRAME_SAMPLES, AUDIO_RATE
from facewire.receiver.audio import AudioSink, CallSound, NullSink, open_device

logger = logging.getLogger(__name__)

#: A peer's queue holds at most this much (ms): beyond it, its oldest sound is dropped, so a
#: device whose clock runs slower than the playouts' cannot make the latency grow.
MAX_QUEUED_MS = 200
MAX_QUEUED = MAX_QUEUED_MS * AUDIO_RATE // 1000


class MixerInput:
    """One peer's way into the mixer: an AudioSink whose steps wait for the device."""

    def __init__(self, mixer: Mixer, name: str) -> None:
        self._mixer = mixer
        self.name = f"{mixer.name}, mixed"
        # From write to the speaker: the device's own latency and, on average, one step in
        # the queue before the callback takes it.
        self.latency_us = mixer.latency_us + AUDIO_FRAME_MS * 1000
        self.peer = name
        self._chunks: deque[np.ndarray] = deque()
        self._queued = 0
        self.dropped = 0  # samples dropped because the queue was full

    def write(self, pcm: np.ndarray) -> None:
        with self._mixer.lock:
            self._chunks.append(np.asarray(pcm, np.int16))
            self._queued += len(pcm)
            while self._queued > MAX_QUEUED:
                oldest = self._chunks.popleft()
                self._queued -= len(oldest)
                self.dropped += len(oldest)

    def take(self, count: int) -> np.ndarray:
        """The next ``count`` samples (silence where the queue runs out); the mixer's lock held."""
        out = np.zeros(count, np.int16)
        at = 0
        while at < count and self._chunks:
            chunk = self._chunks[0]
            n = min(count - at, len(chunk))
            out[at : at + n] = chunk[:n]
            at += n
            if n == len(chunk):
                self._chunks.popleft()
            else:
                self._chunks[0] = chunk[n:]
        self._queued -= at
        return out

    def close(self) -> None:
        self._mixer.remove(self)


class Mixer:
    """Sums its inputs into one stream of 48 kHz mono int16 (:meth:`fill`)."""

    def __init__(self, name: str = "mixer", latency_us: int = 0) -> None:
        self.name = name
        self.latency_us = latency_us
        self.lock = threading.Lock()
        self._inputs: list[MixerInput] = []

    def input(self, peer: str) -> MixerInput:
        made = MixerInput(self, peer)
        with self.lock:
            self._inputs.append(made)
        return made

    def remove(self, gone: MixerInput) -> None:
        with self.lock:
            if gone in self._inputs:
                self._inputs.remove(gone)

    def fill(self, count: int) -> np.ndarray:
        """The next ``count`` samples: every input's, added, clipped to int16."""
        total = np.zeros(count, np.int32)
        with self.lock:
            for source in self._inputs:
                total += source.take(count)
        return np.clip(total, -32768, 32767).astype(np.int16)


class DeviceMixer(Mixer):
    """A mixer played on the default output device: PortAudio's callback pulls :meth:`fill`."""

    def __init__(self) -> None:
        import sounddevice as sd

        def callback(outdata: np.ndarray, frames: int, time: Any, status: Any) -> None:
            outdata[:, 0] = self.fill(frames)

        stream = sd.OutputStream(
            samplerate=AUDIO_RATE,
            channels=1,
            dtype="int16",
            blocksize=AUDIO_FRAME_SAMPLES,
            callback=callback,
        )
        super().__init__(
            str(sd.query_devices(kind="output")["name"]), round(float(stream.latency) * 1e6)
        )
        self._stream = stream
        stream.start()

    def close(self) -> None:
        self._stream.close()


def open_mixer() -> tuple[DeviceMixer | None, str | None]:
    """The sound device's mixer, or None and one line saying why there is none."""
    return open_device(DeviceMixer)


class RoomSound:
    """The room's one sound device (or none) and a :class:`CallSound` per peer."""

    def __init__(self, notify: Callable[[str], None], device: bool = True) -> None:
        self._notify = notify
        self.mixer: DeviceMixer | None = None
        self._no_device: str | None = None
        if device:
            self.mixer, self._no_device = open_mixer()

    def for_peer(self, name: str, shown: list[tuple[int, int]], fps: float) -> CallSound:
        """``name``'s sound; ``shown``: its pictures' (shown µs, captured µs), appended to
        as they are drawn; the recording's frame 0 is the peer's first frame told to it."""
        sink: AudioSink = self.mixer.input(name) if self.mixer is not None else NullSink()
        return CallSound(shown, 0, fps, self._notify, sink=sink)

    def heard(self) -> None:
        """A peer's sound came: say once that there is no device to play it on."""
        if self._no_device is not None:
            self._notify(self._no_device)
            self._no_device = None

    def close(self) -> None:
        if self.mixer is not None:
            self.mixer.close()
