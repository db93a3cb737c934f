"""Where the picture loses detail: each step of the call's geometry path, scored alone.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_ablation.py [--input CLIP ...] [--frames N]

Both ends run in one process (as benchmarks/bench_rem.py), and every frame is drawn by the
receiver's own renderer, over the same warped surroundings and camera motion, from the face
as each step leaves it:

1. landmarks: the tracked landmarks themselves, no fitting (the ceiling of a mesh with the
   snapshot's texture);
2. wires: the least-squares fit of all wire parameters (seed 000), unquantised;
3. wire basis: that fit projected on the rig's 16-coefficient wire basis;
4. smoothed: the channels after the sender's One Euro filter, before quantisation;
5. the call: quantised, through packets and the receiver's decoder (REM off), drawn without
   the face's edge corrections (models/edge.py);
6. + the face's edge: the same packets drawn with them, as the receiver does;
7. + REM: the same with the live eye and mouth patches.

Per row: SSIM / PSNR over the face, eyes, mouth and mouth-open regions (masks from the
input's own landmarks, benchmarks/bench_rem.py), and the bit rate where packets are sent.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_rem import REGIONS, call, scores  # noqa: E402

from facewire.loopback import Loopback  # noqa: E402
from facewire.models.face_channels import WIRE, pose_from_channels  # noqa: E402
from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path  # noqa: E402
from facewire.sender.encoder import FaceEncoder  # noqa: E402
from facewire.sender.landmarks import LandmarkTracker  # noqa: E402

EDGE = "+ the face's edge"
STEPS = ("landmarks", "wires", "wire basis", "smoothed", "the call", EDGE)


def geometry_steps(
    frames: list[CapturedFrame], size: tuple[int, int], fps: float
) -> tuple[dict[str, list[np.ndarray]], int, float]:
    """Every frame drawn from each geometry step (REM off); the packets' bytes, and the edge
    corrections' share of them."""
    encoder = FaceEncoder(size[0], size[1], fps, rem=False)
    outputs: dict[str, list[np.ndarray]] = {step: [] for step in STEPS}
    sent = 0
    last: dict[str, np.ndarray] = {}
    with Loopback(encoder, frames[0]) as both:
        decoder = both.decoder
        for frame in frames:
            result = encoder.analyse(frame.image)
            packets = both.send_analysed(frame, result)
            both.receive(packets)
            sent += sum(len(data) for data in packets)
            values = both.shown
            assert values is not None, "the first frame sent nothing"
            camera = decoder.camera(values)
            if result is not None and encoder.points is not None and encoder.intended:
                pose, params = result
                coefficients = encoder.projected(params)
                smooth = encoder.intended
                drawn = {
                    "landmarks": encoder.points,
                    "wires": pose.apply(decoder.wires.deform(params)),
                    "wire basis": pose.apply(
                        decoder.wires.deform(
                            encoder.rest_params + encoder.basis.params(coefficients)
                        )
                    ),
                    "smoothed": pose_from_channels(smooth).apply(
                        decoder.wires.deform(
                            encoder.rest_params + encoder.basis.params(smooth[WIRE])
                        )
                    ),
                }
                for step, vertices in drawn.items():
                    last[step] = decoder.draw_vertices(vertices, camera)
            last[EDGE] = decoder.reconstruct(values)
            last["the call"] = decoder.draw_vertices(decoder.image_vertices(values), camera)
            for step in STEPS:
                outputs[step].append(last.get(step, last["the call"]))
    return outputs, sent, encoder.edge_bytes


def bench_clip(path: Path, frames_limit: int | None) -> None:
    with VideoSource(path) as video:
        fps, size = video.fps, (video.width, video.height)
        frames = [
            CapturedFrame(f.index, f.image, round(f.index * 1e6 / fps))
            for f in video.frames(limit=frames_limit)
        ]
    inputs = [f.image for f in frames]
    tracker = LandmarkTracker()
    points = [None if (t := tracker.track(img)) is None else t.points for img in inputs]
    outputs, sent, edge_bytes = geometry_steps(frames, size, fps)
    rem = call(frames, size, fps, rem=True)
    outputs["+ REM"] = rem.outputs
    duration = len(frames) / fps
    print(f"{path.name} ({size[0]}x{size[1]}, {len(frames)} frames), against the input:")
    print("| step | " + " | ".join(f"{r} SSIM / PSNR" for r in REGIONS) + " | geometry |")
    print("|---|" + "---|" * (len(REGIONS) + 1))
    for step, out in outputs.items():
        s = scores(inputs, out, points)
        cells = " | ".join(f"{s[r][0]:.4f} / {s[r][1]:.2f} dB" for r in REGIONS)
        rate = ""
        if step == "the call":
            rate = f"{(sent - edge_bytes) * 8 / duration / 1000:.2f} kbit/s"
        elif step == EDGE:
            rate = f"+ edge {edge_bytes * 8 / duration / 1000:.2f} kbit/s"
        elif step == "+ REM":
            rate = f"+ REM {rem.rem_bytes * 8 / duration / 1000:.2f} kbit/s"
        print(f"| {step} | {cells} | {rate} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--input", type=Path, action="append")
    parser.add_argument("--frames", type=int)
    args = parser.parse_args()
    for path in args.input or [demo_clip_path()]:
        bench_clip(path, args.frames)


if __name__ == "__main__":
    main()
