"""Time both ends of a call on the bundled clip, and how close the rebuild is to the truth.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_call.py [--threads T] [--no-rem]

Sender: track + pose + wire fit + basis projection + quantise + channel coding + REM patches
(cut, change detection, WebP) + packet bytes, per frame. Receiver: decode + dequantise + wire
deformation + pose + REM patches (decode, colour adaptation, merge, texture upload) + the warp
of the head's surroundings (person and scene layers, camera) + render over it, per frame.
Accuracy: rebuilt rig markers against the clip's ground-truth marker positions (pixels), and
the eyelid gap of the mesh at the scripted blinks (the REM patches' lids are measured by
bench_rem.py). Glass-to-glass latency over sockets comes from `facewire demo --stats`.
"""

from __future__ import annotations

import argparse
import os
import time

import cv2
import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from facewire.protocol.packets import decode  # noqa: E402
from facewire.receiver.decoder import FaceDecoder  # noqa: E402
from facewire.sender.capture import VideoSource, demo_clip_path  # noqa: E402
from facewire.sender.encoder import FaceEncoder  # noqa: E402


def _ms(samples: list[float]) -> str:
    a = np.asarray(samples) * 1000
    med, p90 = np.median(a), np.percentile(a, 90)
    return f"median {med:.2f} ms, p90 {p90:.2f} ms ({1000 / med:.0f} fps)"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1)")
    parser.add_argument("--no-rem", action="store_true", help="no REM patches (to compare)")
    args = parser.parse_args()
    cv2.setNumThreads(args.threads)
    truth = dict(np.load(demo_clip_path().with_name("demo_clip_truth.npz")))
    with VideoSource(demo_clip_path()) as video:
        frames = list(video.frames())
        encoder = FaceEncoder(video.width, video.height, video.fps, rem=not args.no_rem)
    t0 = time.perf_counter()
    snapshot = encoder.start(frames[0])
    t_start = time.perf_counter() - t0
    assert snapshot is not None
    t0 = time.perf_counter()
    decoder = FaceDecoder(decode(bytes(snapshot)))  # type: ignore[arg-type]
    t_join = time.perf_counter() - t0

    send, recv, errors, lid = [], [], [], []
    lid_open = 0.0
    sizes: list[int] = []
    rem_sizes: list[int] = []
    markers = truth["marker_vertices"]
    shown = None
    for f in frames:
        t0 = time.perf_counter()
        sent = encoder.encode(f)
        data = b"" if sent is None else bytes(sent)  # None: nothing changed, nothing sent
        patches = [bytes(p) for p in encoder.take_patches()]  # REM patches and refreshes
        send.append(time.perf_counter() - t0)
        sizes.append(len(data))
        rem_sizes.append(sum(len(p) for p in patches))
        t0 = time.perf_counter()
        for patch in patches:
            decoder.offer(decode(patch))
        if data:
            shown = decoder.decode(decode(data))  # type: ignore[arg-type]
        assert shown is not None
        vertices = decoder.image_vertices(shown)
        decoder.reconstruct(shown)  # what a receiver draws: face, surround warp, camera
        recv.append(time.perf_counter() - t0)
        visible = truth["marker_visible"][f.index]
        err = np.linalg.norm(vertices[markers, :2] - truth["marker_xy"][f.index], axis=1)
        errors.append(err[visible])
        if f.index == 0:
            lid_open = float(np.linalg.norm(vertices[159, :2] - vertices[145, :2]))
        if f.index in truth["blink_frames"]:
            lid.append(np.linalg.norm(vertices[159, :2] - vertices[145, :2]))
    decoder.close()

    err = np.concatenate(errors)
    width = np.ptp(truth["marker_xy"][0][:, 0])
    print(f"clip: {len(frames)} frames {video.width}x{video.height}, OpenCV threads {args.threads}")
    print(
        f"session start (sender, once): {t_start * 1000:.0f} ms; "
        f"receiver join: {t_join * 1000:.0f} ms"
    )
    print(f"snapshot: {len(bytes(snapshot)) / 1024:.1f} KiB")
    print(f"sender per frame:   {_ms(send)}")
    print(f"receiver per frame: {_ms(recv)}")
    fps = float(truth["fps"])
    print(
        f"frame packets: {np.mean(sizes):.1f} bytes per frame on average = "
        f"{np.mean(sizes) * 8 * fps / 1000:.1f} kbit/s at {fps:g} fps"
    )
    print(
        f"REM patches: {sum(1 for s in rem_sizes if s)} frames with some, "
        f"{np.mean(rem_sizes) * 8 * fps / 1000:.2f} kbit/s"
    )
    print(
        f"marker error (px, markers spread over {width:.0f} px): median {np.median(err):.2f}, "
        f"p90 {np.percentile(err, 90):.2f}, max {err.max():.2f}"
    )
    print(
        f"eyelid gap (px) rebuilt at frame 0: {lid_open:.1f}; at the scripted blinks "
        f"(lids closed in the clip): {np.round(lid, 1).tolist()}"
    )


if __name__ == "__main__":
    main()
