"""Milliseconds per frame for each stage of both ends, at the sizes cameras give.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_camera_sizes.py [--frames N] [--clips DIR]
    [--only NAME ...]

Makes copies of the bundled clip (640x480) at camera sizes, then runs both ends in one
process (no sockets, OpenCV on one thread) and times each stage of each frame as CPU time of
the thread that runs it (the scene's and the body's motion are followed on a thread beside
the tracker; llvmpipe rasterises the face on its own threads while the surroundings are
warped), and each end's frame as wall time:

- padded to 1280x720 and 1920x1080 (its edges repeated): the face keeps its size while the
  frame grows, so a stage whose time grows down this table works on the frame, not the face;
- scaled up to 1280x720 (cropped), 720x1280 (a phone held upright: cropped and padded) and
  1920x1080 (padded at the sides): the face grows with the frame, as it does in a camera.

Sender stages: tracking (landmarks and the eye model), synthesis, fit (pose, wires), camera
motion, body motion, edge measure, REM patches, refreshes (what the model misses). Receiver
stages: surround warp, refreshes shown, render (drawing and compositing), readback, edge
correct, recording (the MP4 encoder, here on this thread).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from facewire.protocol.packets import decode  # noqa: E402
from facewire.receiver import decoder as receiver_decoder  # noqa: E402
from facewire.receiver.decoder import FaceDecoder  # noqa: E402
from facewire.receiver.recorder import Mp4Recorder  # noqa: E402
from facewire.sender.capture import VideoSource, demo_clip_path  # noqa: E402
from facewire.sender.encoder import FaceEncoder  # noqa: E402

SENDER = (
    "tracking",
    "synthesis",
    "fit",
    "camera motion",
    "body motion",
    "edge measure",
    "rem",
    "refresh",
)
RECEIVER = ("surround warp", "refresh shown", "render", "readback", "edge correct", "recording")


def _scaled(size: tuple[int, int], crop: tuple[int, int] | None = None) -> Callable:
    """Scale 640x480 up by ``size``[0] / 640 and keep ``crop`` (width, height) about the face."""

    def shape(image: np.ndarray) -> np.ndarray:
        big = cv2.resize(image, size, interpolation=cv2.INTER_CUBIC)
        if crop is None:
            return big
        h, w = big.shape[:2]
        cx, cy = round(w * 0.5), round(h * 0.5)  # the clip's face sits near its middle
        x0 = int(np.clip(cx - crop[0] // 2, 0, max(w - crop[0], 0)))
        y0 = int(np.clip(cy - crop[1] // 2, 0, max(h - crop[1], 0)))
        part = big[y0 : y0 + crop[1], x0 : x0 + crop[0]]
        ph, pw = crop[1] - part.shape[0], crop[0] - part.shape[1]
        return cv2.copyMakeBorder(
            part, ph // 2, ph - ph // 2, pw // 2, pw - pw // 2, cv2.BORDER_REFLECT_101
        )

    return shape


def _padded(width: int, height: int) -> Callable:
    def shape(image: np.ndarray) -> np.ndarray:
        top, left = (height - image.shape[0]) // 2, (width - image.shape[1]) // 2
        bottom, right = height - image.shape[0] - top, width - image.shape[1] - left
        return cv2.copyMakeBorder(image, top, bottom, left, right, cv2.BORDER_REPLICATE)

    return shape


CLIPS: dict[str, Callable | None] = {
    "640x480": None,
    "padded 1280x720": _padded(1280, 720),
    "padded 1920x1080": _padded(1920, 1080),
    "scaled 1280x720": _scaled((1280, 960), (1280, 720)),
    "scaled 720x1280": _scaled((1280, 960), (720, 1280)),
    "scaled 1920x1080": _scaled((1440, 1080), (1920, 1080)),
}


def make_clip(path: Path, shape: Callable, frames: int) -> None:
    """The bundled clip's first ``frames`` frames through ``shape``, H.264 at CRF 12."""
    import av

    with VideoSource(demo_clip_path()) as video, av.open(str(path), "w") as out:
        stream = None
        for frame in video.frames(frames):
            image = shape(frame.image)
            if stream is None:
                stream = out.add_stream("libx264", rate=round(video.fps))
                stream.width, stream.height = image.shape[1], image.shape[0]
                stream.pix_fmt = "yuv420p"
                stream.options = {"crf": "12", "preset": "fast"}
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="bgr24")):
                out.mux(packet)
        assert stream is not None
        for packet in stream.encode():
            out.mux(packet)


class Stages:
    """CPU and wall seconds per stage of the current frame, from wrapped callables."""

    def __init__(self) -> None:
        self.cpu: dict[str, float] = defaultdict(float)
        self.wall: dict[str, float] = defaultdict(float)

    def wrap(self, owner: Any, name: str, stage: str) -> None:
        inner = getattr(owner, name)

        def timed(*args: Any, **kwargs: Any) -> Any:
            c0, w0 = time.thread_time(), time.perf_counter()
            try:
                return inner(*args, **kwargs)
            finally:
                self.cpu[stage] += time.thread_time() - c0
                self.wall[stage] += time.perf_counter() - w0

        setattr(owner, name, timed)

    def take(self) -> tuple[dict[str, float], dict[str, float]]:
        cpu, wall = dict(self.cpu), dict(self.wall)
        self.cpu.clear()
        self.wall.clear()
        return cpu, wall


def _subtract(times: dict[str, float], whole: str, parts: tuple[str, ...]) -> None:
    """Nested stages: ``whole`` less the ``parts`` timed inside it."""
    times[whole] = times.get(whole, 0.0) - sum(times.get(p, 0.0) for p in parts)


def run(clip: Path, folder: Path, frames: int) -> Iterator[tuple[dict, dict, float]]:
    """Per frame: (cpu, wall) seconds by stage, and the face's width in pixels."""
    stages = Stages()
    with VideoSource(clip) as video:
        captured = list(video.frames(frames))
        encoder = FaceEncoder(video.width, video.height, video.fps)
    snapshot = encoder.start(captured[0])
    assert snapshot is not None
    decoder = FaceDecoder(decode(bytes(snapshot)))  # type: ignore[arg-type]
    stages.wrap(encoder.tracker, "track", "tracking")
    if encoder.synthesis is not None:
        stages.wrap(encoder.synthesis, "refine", "synthesis")
    stages.wrap(encoder, "analyse", "fit")  # less what it calls, below
    stages.wrap(encoder.camera, "follow", "camera motion")  # beside the tracker
    stages.wrap(encoder.camera, "settle", "camera settle")  # in analyse, after it
    if encoder.body is not None:
        stages.wrap(encoder.body, "update", "body motion")
    stages.wrap(encoder.edge, "measure", "edge measure")
    if encoder.rem is not None:
        stages.wrap(encoder.rem, "changed", "rem")
    if encoder.refresh is not None:
        stages.wrap(encoder.refresh, "measure", "refresh")
    stages.wrap(encoder, "encode", "sender frame")
    stages.wrap(decoder, "reconstruct", "receiver frame")
    stages.wrap(decoder.surround, "warp", "surround warp")
    stages.wrap(decoder.refresh, "over", "refresh shown")
    # Drawn before the surroundings' warp and read after it (FaceRenderer.draw): llvmpipe's
    # threads rasterise meanwhile, and their CPU counts in the warp's stage.
    stages.wrap(decoder.renderer, "draw", "render")
    stages.wrap(decoder.renderer, "finish", "render")
    stages.wrap(decoder.renderer, "_read_rgba", "readback")
    stages.wrap(receiver_decoder, "correct", "edge correct")
    out = folder / f"{clip.stem}-received.mp4"  # beside the clip, never over it
    recorder = Mp4Recorder(out, video.width, video.height, video.fps)
    stages.wrap(recorder, "write", "recording")
    shown = None
    try:
        for frame in captured:
            sent = encoder.encode(frame)
            for patch in encoder.take_patches():
                decoder.offer(decode(bytes(patch)))  # REM patches and refreshes
            if sent is not None:
                shown = decoder.decode(decode(bytes(sent)))  # type: ignore[arg-type]
            assert shown is not None
            recorder.write(decoder.reconstruct(shown))
            cpu, wall = stages.take()
            for times in (cpu, wall):
                _subtract(times, "fit", ("tracking", "synthesis", "camera settle"))
                times["camera motion"] = times.get("camera motion", 0) + times.pop(
                    "camera settle", 0
                )
                _subtract(times, "render", ("readback",))
            outline = decoder.image_vertices(shown)[decoder.mesh.outline]
            yield cpu, wall, float(np.ptp(outline[:, 0]))
    finally:
        recorder.close()
        decoder.close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--clips", type=Path, help="keep the clips made here (default: a temp dir)")
    p.add_argument("--only", nargs="*", help="clip names to run (default: all)")
    args = p.parse_args()
    cv2.setNumThreads(1)
    names = list(CLIPS) if not args.only else args.only
    header = "stage (CPU ms, median)".ljust(24) + "".join(n.rjust(18) for n in names)
    columns: dict[str, dict[str, float]] = {}
    faces: dict[str, float] = {}
    walls: dict[str, tuple[float, ...]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = args.clips or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        for name in names:
            shape = CLIPS[name]
            clip = demo_clip_path()
            if shape is not None:
                clip = folder / (name.replace(" ", "_") + ".mp4")
                if not clip.exists():
                    make_clip(clip, shape, args.frames)
            rows = list(run(clip, folder, args.frames))[5:]  # the first frames warm caches
            columns[name] = {
                s: 1000 * float(np.median([cpu.get(s, 0.0) for cpu, _, _ in rows]))
                for s in (*SENDER, *RECEIVER)
            }
            faces[name] = float(np.median([face for _, _, face in rows]))
            send = [w["sender frame"] for _, w, _ in rows]
            recv = [w["receiver frame"] + w["recording"] for _, w, _ in rows]
            # Medians, means and p90s: the refreshes are compared every fourth frame only.
            walls[name] = tuple(
                1000 * float(f(t)) for f in (np.median, np.mean, _p90) for t in (send, recv)
            )
    print(f"load average {os.getloadavg()[0]:.2f}; {args.frames} frames per clip")
    print(header)
    print("face width (px)".ljust(24) + "".join(f"{faces[n]:18.0f}" for n in names))
    for stage in (*SENDER, *RECEIVER):
        print(stage.ljust(24) + "".join(f"{columns[n][stage]:18.2f}" for n in names))
    labels = (
        "sender wall ms",
        "receiver wall ms",
        "sender wall ms, mean",
        "receiver, mean",
        "sender wall ms, p90",
        "receiver, p90",
    )
    for index, label in enumerate(labels):
        print(label.ljust(24) + "".join(f"{walls[n][index]:18.2f}" for n in names))


def _p90(values: list[float]) -> float:
    return float(np.percentile(values, 90))


if __name__ == "__main__":
    main()
