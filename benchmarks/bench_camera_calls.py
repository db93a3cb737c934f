"""Calls at the sizes cameras give: 1280x720, 720x1280 (a phone held upright) and 1920x1080.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_camera_calls.py [--frames N] [--clips DIR]
    [--only NAME ...]

Makes the copies of the bundled clip that benchmarks/bench_camera_sizes.py times stage by
stage, then calls each as a person would: ``facewire receive --record`` and ``facewire send
--input`` as two processes on 127.0.0.1 (plain, paced at the clip's 30 fps, the default
``--max-size`` 1280x720, so 1920x1080 is sent at 1280x720). Prints the size the receiver
rendered, the frames it rendered, both ends' frame rates (frames over their own busy time),
the glass-to-glass latency and the load average around the call: both ends share this
machine's two cores with whatever else runs. ``--max-kbps`` is the sender's: at its default
(32 kbit/s) two frames share a datagram, and each is drawn one frame interval later than with
a datagram each (``--max-kbps 48``).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import cv2
from bench_camera_sizes import CLIPS, make_clip
from bench_large_input import call

from facewire.sender.session import capped_size


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--clips", type=Path, help="keep the clips made here (default: a temp dir)")
    p.add_argument("--only", nargs="*", help="clip names (default: all but 640x480)")
    p.add_argument(
        "--max-kbps",
        type=float,
        help="the sender's budget (default its own, 32: two frames a datagram; 48 sends one)",
    )
    args = p.parse_args()
    names = args.only or [n for n in CLIPS if n != "640x480"]
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.clips or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for name in names:
            shape = CLIPS[name]
            assert shape is not None, "the bundled clip is `facewire demo`'s own"
            clip = folder / f"{name.replace(' ', '_')}-{args.frames}.mp4"
            if not clip.exists():
                make_clip(clip, shape, args.frames)
            video = cv2.VideoCapture(str(clip))
            width, height = capped_size(int(video.get(3)), int(video.get(4)), 1280, 720)
            video.release()
            before = os.getloadavg()[0]
            budget = () if args.max_kbps is None else ("--max-kbps", f"{args.max_kbps:g}")
            stats, sender = call(clip, folder, "1280x720", args.frames, budget)
            lat = stats["latency_ms"]
            rendered = stats["frames_out"] - stats["frames_held"]
            print(
                f"{name}: rendered at {width}x{height}, {rendered} of "
                f"{stats['frames_out']} frames, receiver {stats['receiver_fps']:.0f} fps, "
                f"{sender}, latency p50 {lat['p50']:.0f} ms p99 {lat['p99']:.0f} ms; load "
                f"{before:.1f} before, {os.getloadavg()[0]:.1f} after"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
