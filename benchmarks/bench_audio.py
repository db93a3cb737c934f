"""Sound figures: bit rate, speech quality after a call's recording, and under packet loss.

1. Bit rate: the bundled clip's speech coded as the sender sends it (Opus, 20 ms frames,
   FEC, sender-side DTX), per setting: while talking and over the whole clip, Opus payload
   and the audio channel (AudioFrame headers included).
2. ``--recording FILE.mp4`` (a call's recording of the bundled clip, e.g. ``facewire demo``'s
   output): its sound against the input speech after alignment: lag, correlation, SNR, and
   PESQ (ITU-T P.862 wide band, ``pesq``) and STOI (``pystoi``) where installed.
3. Loss: the talking part through the receiver's AudioPlayout (real clock, null sink) with
   ``--loss`` percent of packets dropped at random (seeded), concealed by the codec, against
   the input: correlation, SNR, PESQ/STOI.

    .venv/bin/python benchmarks/bench_audio.py [--recording demo-output.mp4] [--loss 5]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.signal import correlate, resample_poly

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from facewire.protocol.constants import AUDIO_RATE  # noqa: E402
from facewire.protocol.packets import AudioFrame, KeyFrame  # noqa: E402
from facewire.receiver.audio import AudioPlayout, NullSink, read_audio  # noqa: E402
from facewire.sender.audio import AudioSender, AudioSettings, demo_speech_path, open_track  # noqa: E402

RATE = 16_000
TALK = (300, 420)  # 20 ms steps of the clip's talking (6.0 - 8.4 s)


def coded(settings: AudioSettings) -> list[AudioFrame]:
    out: list[AudioFrame] = []
    track = open_track(demo_speech_path())
    assert track is not None
    sender = AudioSender(track, out.append, settings)
    for i in range(301):
        sender.send_until(i / 30, i / 30, round(i * 1e6 / 30))
    return out


def align(out: np.ndarray, ref: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    n = min(len(out), len(ref))
    c = correlate(out[:n], ref[:n], mode="full", method="fft")
    lag = int(np.argmax(c)) - (n - 1)
    a, b = (out[lag:n], ref[: n - lag]) if lag >= 0 else (out[: n + lag], ref[-lag:n])
    return lag, a, b


def scores(out: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """Against ``ref`` after alignment; both 16 kHz float."""
    lag, a, b = align(out, ref)
    gain = float(a @ b / (b @ b))
    err = a - gain * b
    res = {
        "lag_ms": lag / RATE * 1000,
        "corr": float(np.corrcoef(a, b)[0, 1]),
        "snr_db": float(10 * np.log10((gain * b) @ (gain * b) / (err @ err))),
    }
    try:
        from pesq import pesq

        res["pesq_wb"] = float(pesq(RATE, b / 32768, a / 32768, "wb"))
    except ImportError:
        pass
    try:
        from pystoi import stoi

        res["stoi"] = float(stoi(b, a, RATE))
    except ImportError:
        pass
    return res


def show(name: str, s: dict[str, float]) -> None:
    print(f"{name}: " + ", ".join(f"{k} {v:.3f}" for k, v in s.items()))


def play(packets: list[AudioFrame], lost: set[int]) -> np.ndarray:
    playout = AudioPlayout(NullSink(), lambda: 60_000)
    shift = time.monotonic_ns() // 1000 - packets[0].capture_us
    playout.push(KeyFrame(0, 1, 0, packets[0].capture_us + shift, b""))
    for p in packets:
        if p.seq in lost:
            continue
        playout.push(AudioFrame(p.seq, p.capture_us + shift, p.data), p.capture_us + shift)
    time.sleep((packets[-1].seq - packets[0].seq + 1) * 0.02 + 0.4)
    playout.close()
    pcm = playout.recorded(0, 30.0).astype(float)
    playout.discard()
    return resample_poly(pcm, RATE, AUDIO_RATE)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recording", type=Path)
    parser.add_argument("--loss", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()

    print("bit rate (bundled clip's speech, 10 s, 2.4 s of talking):")
    for settings in (AudioSettings(), AudioSettings(fec=False), AudioSettings(bitrate=24_000)):
        packets = coded(settings)
        talking = [p for p in packets if TALK[0] <= p.seq < TALK[1]]
        talk_s = (TALK[1] - TALK[0]) * 0.02
        opus = sum(len(p.data) for p in talking) * 8 / talk_s / 1000
        channel = sum(len(bytes(p)) for p in talking) * 8 / talk_s / 1000
        whole = sum(len(bytes(p)) for p in packets) * 8 / 10 / 1000
        print(
            f"  {settings.bitrate / 1000:g} kbit/s, fec {settings.fec}: talking: Opus {opus:.1f}"
            f" kbit/s, channel {channel:.1f} kbit/s; whole clip (DTX): channel {whole:.2f} kbit/s,"
            f" {len(packets)} of 500 frames sent"
        )

    ref = read_audio(demo_speech_path(), RATE).astype(float)
    if args.recording is not None:
        recorded = read_audio(args.recording, RATE).astype(float)
        show(f"recording {args.recording} vs input", scores(recorded, ref))

    packets = [p for p in coded(AudioSettings()) if TALK[0] - 10 <= p.seq < TALK[1] + 10]
    rng = np.random.default_rng(args.seed)
    lost = {p.seq for p in packets if rng.random() < args.loss / 100}
    clean = play(packets, set())
    talk_ref = ref[int((TALK[0] - 10) * 0.02 * RATE) : int((TALK[1] + 10) * 0.02 * RATE)]
    show("playout, no loss, vs input", scores(clean, talk_ref))
    print(f"{args.loss:g}% loss (seed {args.seed}): {len(lost)} of {len(packets)} packets lost")
    show("  concealed by Opus, vs input", scores(play(packets, lost), talk_ref))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
