"""How a call holds up as the head turns and moves: SSIM binned by head yaw and by distance.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_head_motion.py --input CLIP
           [--evaluate OUT.mp4] [--output OUT.mp4]

Runs ``facewire demo --input CLIP --output OUT.mp4`` (a real loopback call, paced), scores
every frame with facewire.quality (face and head regions from the input's own landmarks),
and tracks the input as the sender does to get each frame's head pose relative to the first
frame: the yaw (turn left or right, degrees) and how far the face's centre has moved, as a
fraction of the frame's width. Prints the mean face and head SSIM of the frames in each bin
of yaw and of distance, and the worst frames. ``--evaluate`` scores an existing output.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from facewire.quality import score_videos  # noqa: E402
from facewire.sender.capture import VideoSource  # noqa: E402
from facewire.sender.encoder import FaceEncoder  # noqa: E402

YAW_BINS = (0.0, 10.0, 20.0, 30.0, 90.0)
MOVE_BINS = (0.0, 0.1, 0.2, 1 / 3, 2.0)


def head_motion(clip: Path) -> tuple[np.ndarray, np.ndarray]:
    """Per input frame: |yaw| in degrees and the face centre's distance from its place at the
    first tracked frame, in frame widths (NaN where no face was tracked)."""
    with VideoSource(clip) as video:
        frames = list(video.frames())
        encoder = FaceEncoder(video.width, video.height, video.fps)
        width = video.width
    yaw = np.full(len(frames), np.nan)
    move = np.full(len(frames), np.nan)
    first = next((f for f in frames if encoder.start(f) is not None), None)
    if first is None:
        raise SystemExit(f"no face in {clip}")
    assert encoder.session is not None
    start_rotation, start_centre = None, None
    for i, f in enumerate(frames):
        found = encoder.analyse(f.image)
        if found is None:
            continue
        pose = found[0]
        centre = pose.apply(encoder.session.mesh.vertices)[:, :2].mean(axis=0)
        if start_rotation is None:
            start_rotation, start_centre = pose.rotation, centre
        relative = pose.rotation @ start_rotation.T
        yaw[i] = abs(np.degrees(np.arctan2(relative[0, 2], relative[2, 2])))
        move[i] = np.linalg.norm(centre - start_centre) / width
    return yaw, move


def print_bins(name: str, values: np.ndarray, edges: tuple[float, ...], ssim: dict) -> None:
    print(f"{name:<22} frames  face SSIM  head SSIM")
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        pick = (values >= lo) & (values < hi)
        if not pick.any():
            continue
        face, head = (np.nanmean(np.asarray(ssim[r])[pick]) for r in ("face", "head"))
        print(f"  {lo:5.2f} - {hi:5.2f}        {pick.sum():5d}  {face:9.4f}  {head:9.4f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--input", type=Path, required=True)
    parser.add_argument("--evaluate", type=Path, metavar="OUT.mp4", help="score this, no call")
    parser.add_argument("--output", type=Path, metavar="OUT.mp4", help="keep the call's output")
    args = parser.parse_args()
    clip = args.input.resolve()
    with tempfile.TemporaryDirectory() as tmp:
        output = args.evaluate or (args.output or Path(tmp) / "out.mp4").resolve()
        if not args.evaluate:
            cmd = [sys.executable, "-m", "facewire", "demo", "--input", str(clip)]
            cmd += ["--output", str(output), "--compare", ""]
            done = subprocess.run(cmd, capture_output=True, text=True, check=False)
            if done.returncode != 0:
                raise SystemExit(f"facewire demo failed: {done.stderr.strip()}")
            print(done.stdout.strip().splitlines()[0])
        report = score_videos(clip, output)
    yaw, move = head_motion(clip)
    n = min(len(yaw), report.frames)
    ssim = {r: np.asarray(report.ssim[r][:n]) for r in ("face", "head")}
    print(
        f"{clip.name}: {n} frames, yaw up to {np.nanmax(yaw):.0f} degrees, moves up to "
        f"{np.nanmax(move):.2f} of the width"
    )
    print_bins("|yaw|, degrees", yaw[:n], YAW_BINS, ssim)
    print_bins("moved, frame widths", move[:n], MOVE_BINS, ssim)
    worst = np.argsort(np.nan_to_num(ssim["head"], nan=np.inf))[:5]
    print(
        "worst head SSIM: "
        + ", ".join(
            f"frame {i} {ssim['head'][i]:.3f} (yaw {yaw[i]:.0f}, moved {move[i]:.2f})"
            for i in worst
        )
    )


if __name__ == "__main__":
    main()
