"""Snapshot size: what a call sends once, by part, on clips.

Usage: python benchmarks/bench_snapshot.py [CLIP ...]   (default: the bundled clip)

Starts the sender's encoder on each clip's first frame with a face and prints the snapshot's
bytes as sent (msgpack, with the header byte), split into texture, background and mesh
vertices, with the texture's side and the face's width. Budget (issue 8): at most 12 KB for a
176x144 call and 40 KB for 640x480.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from facewire.protocol.images import image_size
from facewire.sender.capture import VideoSource, demo_clip_path
from facewire.sender.encoder import FaceEncoder


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("clips", nargs="*", type=Path)
    args = parser.parse_args()
    for clip in args.clips or [demo_clip_path()]:
        with VideoSource(clip) as video:
            encoder = FaceEncoder(video.width, video.height, video.fps)
            for frame in video.frames(limit=60):
                snapshot = encoder.start(frame)
                if snapshot is not None:
                    break
            else:
                print(f"{clip.name}: no face in the first 60 frames")
                continue
        codec, side, _ = image_size(snapshot.texture)
        total = len(bytes(snapshot))
        parts = {
            "texture": len(snapshot.texture),
            "background": len(snapshot.background),
            # As the packet codes them (against the canonical mesh), not the array's size.
            "vertices": len(snapshot.vertex_bytes()),
        }
        rest = total - sum(parts.values())
        print(
            f"{clip.name} {video.width}x{video.height}: snapshot {total / 1000:.1f} KB = "
            + ", ".join(f"{k} {v / 1000:.1f}" for k, v in parts.items())
            + f", rest {rest / 1000:.1f} (texture {codec} {side}x{side})"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
