"""A call across cuts: clips one after another, each a new scene.

Usage:
  PYOPENGL_PLATFORM=egl python benchmarks/bench_scene_cut.py --input CLIP --input CLIP ...
      [--seconds S] [--dissolve D] [--output DIR]

Writes the first S seconds (default 4) of each clip one after another, at the first clip's
size and frame rate, runs ``facewire demo`` on it (two processes, ZeroMQ on loopback, paced
at the frame rate), and prints per cut: seconds from the capture of the new scene's first
frame to its first picture on the receiver's screen (the demo's stats), and the whole frame's
luma SSIM (facewire/quality.py) from 1 s after the cut to the next cut. With ``--dissolve D``
each clip dissolves into the next over D seconds (the one before going on under it) instead
of a cut, and the SSIM is taken from 1 s after the dissolve's end.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from facewire.quality import read_frames, ssim  # noqa: E402


def splice(
    clips: list[Path], seconds: float, out: Path, dissolve: float = 0.0
) -> tuple[list[int], float]:
    """``clips`` one after another in ``out``, each dissolving into the next over ``dissolve``
    seconds; the first frame of each (of its dissolve) and the frame rate."""
    writer, starts, total, fps, size = None, [], 0, 30.0, (0, 0)
    going_on: list[np.ndarray] = []  # the clip before, under the dissolve
    for n, clip in enumerate(clips):
        capture = cv2.VideoCapture(str(clip))
        if writer is None:
            fps = capture.get(cv2.CAP_PROP_FPS) or 30.0
            size = (
                int(capture.get(cv2.CAP_PROP_FRAME_WIDTH)),
                int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT)),
            )
            writer = cv2.VideoWriter(str(out), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
        starts.append(total)
        fade = round(dissolve * fps)
        frames = []
        for _ in range(round(seconds * fps) + fade):
            ok, image = capture.read()
            if not ok:
                break
            if image.shape[1::-1] != size:
                image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
            frames.append(image)
        capture.release()
        for k, before in enumerate(going_on[: len(frames)]):
            share = (k + 1) / (len(going_on) + 1)
            frames[k] = cv2.addWeighted(before, 1.0 - share, frames[k], share, 0.0)
        kept = frames if n == len(clips) - 1 else frames[: len(frames) - fade]
        going_on = frames[len(kept) :]
        for image in kept:
            writer.write(image)
        total += len(kept)
    assert writer is not None
    writer.release()
    return starts, fps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--input", type=Path, action="append", required=True)
    parser.add_argument("--seconds", type=float, default=4.0)
    parser.add_argument("--dissolve", type=float, default=0.0, help="seconds, 0: a cut")
    parser.add_argument("--output", type=Path, help="folder for the clip, output and stats")
    args = parser.parse_args()
    folder = args.output or Path(tempfile.mkdtemp(prefix="scene_cut_"))
    folder.mkdir(parents=True, exist_ok=True)
    clip, out, stats_file = folder / "cuts.mp4", folder / "out.mp4", folder / "stats.json"
    starts, fps = splice(args.input, args.seconds, clip, args.dissolve)
    command = [sys.executable, "-m", "facewire", "demo", "--input", str(clip)]
    command += ["--output", str(out), "--stats", str(stats_file), "--no-sound"]
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    stats = json.loads(stats_file.read_text())
    inputs, outputs = list(read_frames(clip)), list(read_frames(out))
    ends = [*starts[1:], len(inputs)]
    print(f"{clip}: {len(inputs)} frames, cuts at {starts[1:]}; {stats['scenes']} scenes seen")
    print("| cut at frame | first picture after, s | frame SSIM from 1 s after the cut |")
    print("|---|---|---|")
    # Each cut's scene: the first session begun between it and the next cut.
    firsts = dict(zip(stats["scene_frames"], stats["scene_first_s"], strict=False))
    for start, end in zip(starts[1:], ends[1:], strict=True):
        frames = range(start + round((1.0 + args.dissolve) * fps), min(end, len(outputs)))
        score = np.mean([ssim(inputs[i], outputs[i]) for i in frames])
        seen = [firsts[f] for f in sorted(firsts) if start <= f < end]
        first = f"{seen[0]:.2f}" if seen else "none"
        print(f"| {start} | {first} | {score:.3f} |")
    kbps = stats["kbps"]
    print(f"kbit/s: snapshot {kbps['snapshot']:.1f}, total {kbps['total']:.1f}")


if __name__ == "__main__":
    main()
