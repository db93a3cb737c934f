"""How well each way of drawing the lips between two frames puts them where they were.

Usage: .venv/bin/python benchmarks/bench_lip_inbetweens.py [--input CLIP ...] [--every 2,3,4]

Both ends run in one process over the clip (the bundled clip by default), and every frame's
face is rebuilt from the packets, as the receiver has it. Then only every Nth frame is kept
as a key frame (seed 003 section 3.7: key frames every delta-t), and the frames between are
drawn from the two key frames around them. Each way is scored against the face the call sends
for that frame: the RMS distance of the lip rings' vertices (the mouth rig's four contours),
in pixels of the frame, and of the whole mouth region (the rings and the skin that follows
them). The ways:

- **seed 000 blend**: the wire parameters blended feature by feature (the mouth on t^3), as
  the receiver's playout draws pictures between frames;
- **linear**: every parameter blended linearly;
- **homotopy**: the seed 000 blend with the lip rings on seed 003's homotopy sweep between
  the key frames' contours (blending function only, n = 0);
- **homotopy + control vectors**: the same, with the four lip markers' velocities at both key
  frames as the 3D control vectors (Eq. 8-9);
- **homotopy + control vectors, n**: the same with a per-contour blending parameter.

The last column is the median time to build one in-between face's vertices that way (the
homotopy's includes the seed 000 blend it starts from); drawing the picture comes on top.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from facewire.loopback import Loopback  # noqa: E402
from facewire.models.blending import blend  # noqa: E402
from facewire.models.homotopy import MouthRig  # noqa: E402
from facewire.models.pose import Pose  # noqa: E402
from facewire.receiver.decoder import FaceDecoder  # noqa: E402
from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path  # noqa: E402
from facewire.sender.encoder import FaceEncoder  # noqa: E402

#: Per-contour blending parameters tried (outer, ring, ring, inner).
CONTOUR_N = (
    (-0.15,) * 4,
    (-0.3,) * 4,
    (-0.5,) * 4,
    (-0.3, -0.3, -0.15, 0.0),
    (0.0, -0.15, -0.3, -0.3),
)


def sent_faces(path: Path) -> tuple[FaceDecoder, list[tuple[Pose, np.ndarray, np.ndarray]]]:
    """The decoder, and each frame's (pose, wire parameters, lips) as the receiver has them."""
    with VideoSource(path) as video:
        fps, size = video.fps, (video.width, video.height)
        frames = [
            CapturedFrame(f.index, f.image, round(f.index * 1e6 / fps)) for f in video.frames()
        ]
    both = Loopback(FaceEncoder(size[0], size[1], fps, rem=False), frames[0])
    faces = []
    for frame in frames:
        both.step(frame)
        assert both.shown is not None, "the first frame sent nothing"
        faces.append(both.decoder.parameters(both.shown))
    return both.decoder, faces


def score(path: Path, every: list[int]) -> None:
    decoder, faces = sent_faces(path)
    try:
        groups = decoder.wires.feature_groups()
        mouth = MouthRig.from_rig(decoder.mesh, decoder.rig)
        models = [decoder.model(params, lips) for _, params, lips in faces]
        rings = mouth.ring_vertices
        region = np.concatenate([rings, mouth.follow_vertices])
        tuned = {n: MouthRig.from_rig(decoder.mesh, decoder.rig, n=n) for n in CONTOUR_N}

        def seed000(i: int, j: int, t: float) -> np.ndarray:
            (_, pa, la), (_, pb, lb) = faces[i], faces[j]
            lips = blend(la, lb, t, {"mouth": np.arange(len(la))})
            return decoder.model(blend(pa, pb, t, groups), lips)

        def linear(i: int, j: int, t: float) -> np.ndarray:
            (_, pa, la), (_, pb, lb) = faces[i], faces[j]
            return decoder.model((1 - t) * pa + t * pb, (1 - t) * la + t * lb)

        def homotopy(rig: MouthRig, control: bool) -> Callable[[int, int, float, int], np.ndarray]:
            def draw(i: int, j: int, t: float, step: int) -> np.ndarray:
                before = models[i - step] if i - step >= 0 else None
                return rig.between(seed000(i, j, t), models[i], models[j], t, before, control)

            return draw

        ways: dict[str, Callable[[int, int, float, int], np.ndarray]] = {
            "seed 000 blend (the call's playout)": lambda i, j, t, _: seed000(i, j, t),
            "linear": lambda i, j, t, _: linear(i, j, t),
            "homotopy, n = 0": homotopy(mouth, control=False),
            "homotopy + control vectors": homotopy(mouth, control=True),
        }
        for n, rig in tuned.items():
            ways[f"homotopy + control vectors, n = {n}"] = homotopy(rig, control=True)
        print(f"{path.name}: {len(faces)} frames; lip rings / mouth region RMS px")
        header = " | ".join(f"every {k}: rings / region" for k in every)
        print(f"| way | {header} | face built in (median) |")
        print("|---|" + "---|" * (len(every) + 1))
        for name, draw in ways.items():
            cells = []
            spent: list[float] = []
            for step in every:
                ring_err, region_err = [], []
                for a in range(0, len(faces) - step, step):
                    for i in range(a + 1, a + step):
                        start = time.perf_counter()
                        got = draw(a, a + step, (i - a) / step, step)
                        spent.append(time.perf_counter() - start)
                        scale = faces[i][0].scale  # pixels per cm
                        diff = np.linalg.norm(got - models[i], axis=1) * scale
                        ring_err.append(np.mean(diff[rings] ** 2))
                        region_err.append(np.mean(diff[region] ** 2))
                cells.append(
                    f"{np.sqrt(np.mean(ring_err)):.3f} / {np.sqrt(np.mean(region_err)):.3f}"
                )
            ms = f"{1000 * np.median(spent):.2f} ms"
            print(f"| {name} | " + " | ".join(cells) + f" | {ms} |")
    finally:
        decoder.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--input", type=Path, action="append")
    parser.add_argument("--every", default="2,3,4", help="key frame spacings, frames")
    args = parser.parse_args()
    every = [int(k) for k in args.every.split(",")]
    for path in args.input or [demo_clip_path()]:
        score(path, every)


if __name__ == "__main__":
    main()
