"""Clips that speak, and how a recording's voice is told apart (tests of sound in calls)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from facewire.protocol.constants import AUDIO_RATE
from facewire.receiver.audio import mux_audio
from facewire.sender.audio import demo_speech_path, open_track
from facewire.sender.capture import demo_clip_path

#: The bundled clip's talking part: its frames from here on, its speech from 6 s on.
TALKING_FROM_FRAME = 180
TALKING_FROM_S = 6


def demo_speech() -> np.ndarray:
    """The bundled clip's speech, 48 kHz mono int16 (10 s, speaking from 6 s on)."""
    track = open_track(demo_speech_path())
    assert track is not None
    speech = track.read(10 * AUDIO_RATE)
    assert speech is not None
    return speech


def talking_voice(swapped: bool = False) -> np.ndarray:
    """The bundled clip's 4 s of speech; ``swapped``: its two halves the other way round, a
    second voice whose loudness follows another course."""
    voice = demo_speech()[TALKING_FROM_S * AUDIO_RATE :]
    if swapped:
        half = len(voice) // 2
        voice = np.concatenate([voice[half:], voice[:half]])
    return voice


def talking_clip(path: Path, voice: np.ndarray, times: int = 1) -> Path:
    """The bundled clip's talking part (frames 180-299), ``times`` over, with ``voice`` as the
    file's own audio track: a clip that speaks from its first frame, as a call often does."""
    import cv2

    from facewire.sender.capture import VideoSource

    talking = [f.image for f in VideoSource(demo_clip_path()).frames()
               if f.index >= TALKING_FROM_FRAME]  # fmt: skip
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), 30.0, (640, 480))
    for image in talking * times:
        writer.write(image)
    writer.release()
    mux_audio(path, voice)
    return path


def voice_match(recorded: np.ndarray, speech: np.ndarray) -> tuple[float, float]:
    """(correlation, lag in ms) of the loudness of ``recorded`` against ``speech``: RMS over
    10 ms every millisecond, the best lag within 300 ms either way. Two codecs (Opus, then
    the recording's AAC) keep the voice, not its waveform's phase. (Loudness per 5 ms, lags
    in 5 ms steps, scored the same voice 0.95 or 0.75 as it lay on or between that grid.)"""
    hop, window = AUDIO_RATE // 1000, AUDIO_RATE // 100

    def loudness(pcm: np.ndarray) -> np.ndarray:
        energy = np.concatenate([[0.0], np.cumsum(pcm.astype(float) ** 2)])
        starts = np.arange(0, len(pcm) - window + 1, hop)
        return np.sqrt((energy[starts + window] - energy[starts]) / window)

    a, b = loudness(recorded), loudness(speech)
    n = min(len(a), len(b))
    best = (-1.0, 0.0)
    for lag in range(-300, 301):
        x = a[max(lag, 0) : n + min(lag, 0)]
        y = b[max(-lag, 0) : n - max(lag, 0)]
        best = max(best, (float(np.corrcoef(x, y)[0, 1]), float(lag)))
    return best
