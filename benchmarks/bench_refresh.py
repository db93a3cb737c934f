"""Refreshes: how soon what the model misses is shown, what it costs, and what it does to the
rest of the picture.

Usage:
  PYOPENGL_PLATFORM=egl python benchmarks/bench_refresh.py --input CLIP [--input CLIP ...]
      [--frames N] [--object [--place chin|cheek|over] [--hand]] [--pictures DIR]

Each clip runs twice through both ends in one process (facewire/loopback.py: real codecs,
packets as bytes), without refreshes and with them, every frame rebuilt and compared with its
input: face, head and frame SSIM (facewire/quality.py, regions from the input's own
landmarks) and the refreshes' kbit/s. With ``--object`` an object is held up beside the chin
from 1 s to 2 s: a real photographed texture (the flag of tests/fixtures/astronaut_face.jpg,
0.45 face widths wide), pasted in, as no clip here has a hand raised; with ``--hand`` a hand
instead (the left one of tests/fixtures/hands.jpg, fingers up, 0.8 face widths wide, its
white background left out), which the palm detector can find. Then also printed: the frames
from its coming until the receiver shows it (its area within SHOWN_LEVELS of the input, mean
absolute difference 25 at most) and from its going until the scene is back.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import cv2
import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from facewire.loopback import Loopback  # noqa: E402
from facewire.quality import region_masks, ssim  # noqa: E402
from facewire.sender.capture import CapturedFrame  # noqa: E402
from facewire.sender.encoder import FaceEncoder  # noqa: E402
from facewire.sender.landmarks import LandmarkTracker  # noqa: E402

FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures"
FIXTURE = FIXTURES / "astronaut_face.jpg"
HANDS = FIXTURES / "hands.jpg"
#: Of hands.jpg: grey levels above this in every channel are its white background.
WHITE = 225
#: The area counts as shown when within this mean absolute difference of the input (the model
#: misses it by 80-100; a WebP of the striped object keeps 15-20 of it).
SHOWN_LEVELS = 25.0


def read(path: str, count: int) -> tuple[list[np.ndarray], float]:
    video = cv2.VideoCapture(path)
    fps = video.get(cv2.CAP_PROP_FPS) or 30.0
    frames = []
    while len(frames) < count:
        ok, image = video.read()
        if not ok:
            break
        frames.append(image)
    video.release()
    return frames, fps


def hold_object(
    frames: list[np.ndarray], fps: float, place: str = "chin", hand: bool = False
) -> tuple[list[np.ndarray], tuple[slice, slice], int, int]:
    """``frames`` with the object (or a hand) held from 1 s to 2 s beside the chin (``place``
    "chin"), beside the cheek at the eyes' height ("cheek", within the head's reach), or over
    the chin and jaw, half on the face ("over"); its area and the first frames with it and
    without it again."""
    points = LandmarkTracker().track(frames[0])
    if points is None:
        raise SystemExit("no face in the first frame")
    p = points.points
    h, w = frames[0].shape[:2]
    face = float(np.ptp(p[:, 0]))
    if hand:
        photo = cv2.imread(str(HANDS))[:, 50:345]  # the left hand
        ow = max(8, int(0.8 * face))
        oh = round(ow * photo.shape[0] / photo.shape[1])
    else:
        photo = cv2.imread(str(FIXTURE))[150:260, 0:70]  # the flag
        ow = max(8, int(0.45 * face))
        oh = int(1.5 * ow)
    thing = cv2.resize(photo, (ow, oh), interpolation=cv2.INTER_AREA)
    keep = ~(thing.min(axis=2) > WHITE) if hand else np.ones(thing.shape[:2], bool)
    x = min(int(p[:, 0].max() + 0.05 * face), w - ow)
    y = max(0, min(int(p[:, 1].max() - 0.8 * oh), h - oh))
    if place == "cheek":
        eyes = float(p[[33, 263], 1].mean())
        y = max(0, min(int(eyes - 0.5 * oh), h - oh))
    elif place == "over":
        x = min(int(p[:, 0].max() - 0.5 * ow), w - ow)
    area = np.s_[y : y + oh, x : x + ow]
    start, end = round(fps), round(2 * fps)
    out = [f.copy() for f in frames]
    for image in out[start:end]:
        image[area][keep] = thing[keep]
    return out, area, start, end


def run(frames: list[np.ndarray], fps: float, refresh: bool, area, pictures: Path | None, name):
    h, w = frames[0].shape[:2]
    encoder = FaceEncoder(w, h, fps, refresh=refresh)
    tracker = LandmarkTracker()
    scores: dict[str, list[float]] = {"face": [], "head": [], "frame": []}
    errors = []
    with Loopback(encoder, CapturedFrame(0, frames[0], 0)) as call:
        for i, frame in enumerate(frames):
            call.step(CapturedFrame(i, frame, round(i * 1e6 / fps)))
            out = call.picture()
            found = tracker.track(frame)
            masks = region_masks(None if found is None else found.points, frame.shape)
            for region in scores:
                scores[region].append(ssim(frame, out, masks.get(region)))
            if area is not None:
                errors.append(float(np.abs(out[area].astype(int) - frame[area]).mean()))
            if pictures is not None and i % 15 == 0:
                pictures.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(pictures / f"{name}_{i:03d}.png"), np.hstack([frame, out]))
        seconds = len(frames) / fps
        kbps = 0.0 if encoder.refresh is None else encoder.refresh.bytes * 8 / seconds / 1000
    return {k: float(np.nanmean(v)) for k, v in scores.items()}, kbps, errors


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--input", action="append", required=True)
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--object", action="store_true")
    parser.add_argument("--place", choices=("chin", "cheek", "over"), default="chin")
    parser.add_argument("--hand", action="store_true")
    parser.add_argument("--pictures", type=Path)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    for path in args.input:
        frames, fps = read(path, args.frames)
        area, start, end = None, 0, 0
        if args.object:
            frames, area, start, end = hold_object(frames, fps, args.place, args.hand)
        name = Path(path).stem
        for refresh in (False, True):
            tag = f"{name}_{'refresh' if refresh else 'model'}"
            got, kbps, errors = run(frames, fps, refresh, area, args.pictures, tag)
            line = (
                f"{Path(path).name} refreshes {'on ' if refresh else 'off'}: face SSIM "
                f"{got['face']:.4f}, head {got['head']:.4f}, frame {got['frame']:.4f}; "
                f"refreshes {kbps:.2f} kbit/s"
            )
            if area is not None:
                shown = next((i for i in range(start, end) if errors[i] < SHOWN_LEVELS), None)
                back = next((i for i in range(end, len(errors)) if errors[i] < SHOWN_LEVELS), None)
                line += (
                    f"; object shown {'never' if shown is None else shown - start} frames "
                    f"after it came, scene back {'never' if back is None else back - end} "
                    f"frames after it went"
                )
            print(line)


if __name__ == "__main__":
    main()
