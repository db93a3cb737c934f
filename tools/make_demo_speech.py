"""Make the bundled clip's speech track (sender/data/demo_clip_speech.wav).

The clip (sender/data/demo_clip.mp4) talks in frames 180-252: its jaw opens about four times
a second (tools/make_demo_clip.py, ``talk_amount``). This script speaks one short word per
jaw opening with espeak-ng (Debian package ``espeak-ng``, GPL-3 program; its output is
ours), so each word's loudest moment falls on the frame where the mouth is widest and its
loudness follows how wide it opens. The rest of the 10 s is silence.

Output: 16 kHz mono 16-bit WAV, exactly as long as the clip. Deterministic for one
espeak-ng version (1.51 made the committed file). Needs espeak-ng only here, not at run time:

    .venv/bin/python tools/make_demo_speech.py
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import wave
from pathlib import Path

import numpy as np
from scipy.signal import find_peaks, resample_poly

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "sender" / "data" / "demo_clip_speech.wav"
TRUTH = ROOT / "sender" / "data" / "demo_clip_truth.npz"

RATE = 16_000
FPS, N_FRAMES, TALK = 30, 300, (180, 252)
#: One word per jaw opening, in order (monosyllables, so one opening is one syllable).
WORDS = "hi this is face wire can you hear me now all right good".split()
VOICE, SPEED_WPM = "en-us", 170


def talk_amount(f: float) -> float:
    """The clip's jaw opening at (fractional) frame f, as tools/make_demo_clip.py made it."""
    a, b = TALK
    if not a <= f <= b:
        return 0.0
    t = (f - a) / FPS
    env = _smoothstep(min(1.0, (f - a) / 8.0)) * _smoothstep(min(1.0, (b - f) / 8.0))
    syll = 0.5 - 0.5 * np.cos(2 * np.pi * (4.0 * t + 0.4 * np.sin(2 * np.pi * 0.7 * t)))
    amp = 0.5 + 0.6 * (0.5 + 0.5 * np.sin(2 * np.pi * 0.45 * t + 1.0))
    return float(env * syll * amp)


def _smoothstep(x: float) -> float:
    x = min(1.0, max(0.0, x))
    return x * x * (3 - 2 * x)


def speak(word: str, workdir: Path) -> np.ndarray:
    """One word from espeak-ng at 16 kHz, float in [-1, 1], leading/trailing silence cut."""
    path = workdir / f"{word}.wav"
    subprocess.run(
        ["espeak-ng", "-v", VOICE, "-s", str(SPEED_WPM), "-w", str(path), word],
        check=True,
        capture_output=True,
    )
    with wave.open(str(path)) as w:
        rate = w.getframerate()
        pcm = np.frombuffer(w.readframes(w.getnframes()), dtype="<i2").astype(np.float64)
    pcm = resample_poly(pcm / 32768.0, RATE, rate)
    loud = np.flatnonzero(np.abs(pcm) > 0.01)
    return pcm[loud[0] : loud[-1] + 1] if len(loud) else pcm


def envelope_peak(pcm: np.ndarray) -> int:
    """Sample index of the loudest 40 ms of ``pcm`` (where the mouth should be widest)."""
    win = int(0.04 * RATE)
    energy = np.convolve(pcm**2, np.ones(win), mode="same")
    return int(np.argmax(energy))


def jaw_peaks() -> tuple[np.ndarray, np.ndarray]:
    """Times (s) and heights of the clip's jaw openings, found on a 1 ms grid."""
    t = np.arange(TALK[0] / FPS, TALK[1] / FPS, 0.001)
    jaw = np.array([talk_amount(x * FPS) for x in t])
    idx, _ = find_peaks(jaw, height=0.05)
    return t[idx], jaw[idx]


def make_track() -> np.ndarray:
    times, heights = jaw_peaks()
    n = min(len(times), len(WORDS))
    out = np.zeros(N_FRAMES * RATE // FPS)
    with tempfile.TemporaryDirectory() as tmp:
        for word, t, h in zip(WORDS[:n], times[:n], heights[:n], strict=True):
            pcm = speak(word, Path(tmp))
            # Each word no longer than the gap to the next opening (250 ms at 4 Hz).
            pcm = pcm[: int(0.30 * RATE)]
            fade = np.minimum(1.0, np.minimum(np.arange(len(pcm)), np.arange(len(pcm))[::-1]) / 80)
            gain = 0.35 + 0.5 * h / heights.max()
            start = int(round(t * RATE)) - envelope_peak(pcm)
            lo, hi = max(0, start), min(len(out), start + len(pcm))
            out[lo:hi] += (gain * fade * pcm)[lo - start : hi - start]
    peak = np.abs(out).max()
    return out * (0.7 / peak) if peak > 0 else out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    if shutil.which("espeak-ng") is None:
        print("espeak-ng is not installed (apt-get install espeak-ng)", file=sys.stderr)
        return 1
    track = make_track()
    pcm = np.clip(np.round(track * 32767), -32768, 32767).astype("<i2")
    with wave.open(str(args.out), "wb") as w:
        w.setnchannels(1)
        w.setsampwidth(2)
        w.setframerate(RATE)
        w.writeframes(pcm.tobytes())
    print(f"wrote {args.out}: {len(pcm) / RATE:.2f} s at {RATE} Hz, {len(jaw_peaks()[0])} openings")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
