"""Calls of large inputs: 3840x2160 sent as it is or scaled down by the sender, and 1280x720.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_large_input.py [--frames N] [--size WxH]

Makes copies of the bundled clip's first N frames scaled up to 3840x2160 (``--size``) and to
1280x720, then runs ``facewire receive --record`` and ``facewire send --input`` on 127.0.0.1
through the commands: the large copy with ``--max-size`` as large as itself (the whole call at
that size: the receiver renders at the snapshot's size), with the default 1280x720 and with
960x540; the 1280x720 copy with the default. Both ends share this machine's two cores (the
sender decoding the large file takes one). Prints the frames the receiver rendered (the rest
were skipped because a newer frame was waiting, and held), its own frame rate (deform +
render), the sender's, and the glass-to-glass latency.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the call helpers

from cli_call import Facewire, free_ports  # noqa: E402

from facewire.sender.capture import demo_clip_path  # noqa: E402


def make_clip(path: Path, size: tuple[int, int], frames: int) -> None:
    source = cv2.VideoCapture(str(demo_clip_path()))
    fps = source.get(cv2.CAP_PROP_FPS) or 30.0
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), fps, size)
    for _ in range(frames):
        ok, image = source.read()
        if not ok:
            break
        writer.write(cv2.resize(image, size, interpolation=cv2.INTER_CUBIC))
    writer.release()
    source.release()


def call(
    clip: Path, folder: Path, max_size: str, frames: int, send_args: tuple[str, ...] = ()
) -> tuple[dict, str]:
    address = f"tcp://127.0.0.1:{free_ports(2)}"
    stats = folder / f"{clip.stem}-{max_size}.json"
    receiver = Facewire(
        "receive", "--bind", address, "--plain", "--once", "--stats", str(stats),
        "--record", str(folder / f"{clip.stem}-{max_size}.mp4"),
    )  # fmt: skip
    sender = Facewire(
        "send", "--connect", address, "--plain", "--input", str(clip), "--max-size", max_size,
        "--frames", str(frames), "--stats", str(folder / "sender.json"), *send_args,
    )  # fmt: skip
    try:
        if sender.wait(600) != 0 or receiver.wait(120) != 0:
            raise SystemExit(sender.output() + "\n" + receiver.output())
    finally:
        sender.kill()
        receiver.kill()
    sent = json.loads((folder / "sender.json").read_text())
    return json.loads(stats.read_text()), f"sender {sent['sender_fps']:.0f} fps"


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--size", default="3840x2160")
    args = p.parse_args()
    width, height = (int(v) for v in args.size.split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        large, hd = folder / "large.mp4", folder / "hd.mp4"
        make_clip(large, (width, height), args.frames)
        make_clip(hd, (1280, 720), args.frames)
        for clip, max_size in ((large, args.size), (large, "1280x720"), (large, "960x540"),
                               (hd, "1280x720")):  # fmt: skip
            r, sender = call(clip, folder, max_size, args.frames)
            lat = r["latency_ms"]
            rendered = r["frames_out"] - r["frames_held"]
            source = args.size if clip == large else "1280x720"
            print(
                f"input {source}, --max-size {max_size}: {rendered} of {r['frames_out']} frames "
                f"rendered, receiver {r['receiver_fps']:.1f} fps, {sender}, latency p50 "
                f"{lat['p50']:.0f} ms p99 {lat['p99']:.0f} ms max {lat['max']:.0f} ms"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
