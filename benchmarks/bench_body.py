"""The body's own motion: a real clip made into a person leaning back or moving sideways.

Usage:
  PYOPENGL_PLATFORM=egl python benchmarks/bench_body.py --input CLIP [--input CLIP ...]
      [--motion lean|closer|shift|none] [--frames N] [--no-body] [--no-refresh]
      [--pictures DIR]

Each clip's person (the segmentation of models/person.py, frame by frame) is put back over
the scene with the person painted out (tests/body_clip.py): ``lean`` scales the person from
1.3 to 1 about the first frame's face over 2 s (eased) and then holds, a person leaning back
from the camera; ``closer`` from 0.5 to 1, a person leaning in (from where the snapshot's
texture is sharp for a face half as wide); ``shift`` moves them sideways by 15 % of the
frame's width over 2 s; ``none`` leaves the clip as it is. Both ends run in one process
(facewire/loopback.py: real codecs, packets as bytes, no sockets), every frame is rebuilt
and compared with its input: the silhouette (segmentation of the input against that of the
output, IoU; the lowest over the frames and where), face and head SSIM (facewire/quality.py,
regions from the input's own landmarks), and what the ``body`` channel cost (kbit/s of the
frame bodies' coded bits). ``--no-body`` runs the sender without following the body (its
values stay zero: the body moves with the scene, as before the channel); ``--no-refresh``
without the refreshes of what the model misses (sender/refresh.py), to see the body alone.
``--pictures DIR`` writes input | output every 15 frames.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import cv2
import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the clip maker

from body_clip import iou, leaning_clip, silhouette  # noqa: E402

from facewire.loopback import Loopback  # noqa: E402
from facewire.models.body import BODY  # noqa: E402
from facewire.quality import region_masks, ssim  # noqa: E402
from facewire.sender.capture import CapturedFrame  # noqa: E402
from facewire.sender.encoder import FaceEncoder  # noqa: E402
from facewire.sender.landmarks import LandmarkTracker  # noqa: E402

MOVING_S = 2.0


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
    if not frames:
        raise SystemExit(f"{path}: no frames")
    return frames, fps


def moved(frames: list[np.ndarray], motion: str, fps: float) -> list[np.ndarray]:
    found = LandmarkTracker().track(frames[0])
    if found is None:
        raise SystemExit("no face in the first frame")
    centre = tuple(found.points[:, :2].mean(0))
    moving = round(MOVING_S * fps)
    if motion == "lean":
        return leaning_clip(frames, centre, (1.3, 1.0), moving=moving)  # type: ignore[arg-type]
    if motion == "closer":
        return leaning_clip(frames, centre, (0.5, 1.0), moving=moving)  # type: ignore[arg-type]
    if motion == "shift":
        width = frames[0].shape[1]
        shift = ((0.0, 0.0), (0.15 * width, 0.0))
        return leaning_clip(frames, centre, (1.0, 1.0), shift, moving)  # type: ignore[arg-type]
    return frames


def run(
    frames: list[np.ndarray],
    fps: float,
    body: bool,
    refresh: bool,
    pictures: Path | None,
    name: str,
) -> dict[str, float]:
    h, w = frames[0].shape[:2]
    encoder = FaceEncoder(w, h, fps, body=body, refresh=refresh)
    tracker = LandmarkTracker()
    ious, face, head = [], [], []
    with Loopback(encoder, CapturedFrame(0, frames[0], 0)) as call:
        for i, frame in enumerate(frames):
            call.step(CapturedFrame(i, frame, round(i * 1e6 / fps)))
            out = call.picture()
            ious.append(iou(silhouette(frame), silhouette(out)))
            found = tracker.track(frame)
            masks = region_masks(None if found is None else found.points, frame.shape)
            face.append(ssim(frame, out, masks["face"]))
            head.append(ssim(frame, out, masks["head"]))
            if pictures is not None and (i % 15 == 0 or i == len(frames) - 1):
                pictures.mkdir(parents=True, exist_ok=True)
                cv2.imwrite(str(pictures / f"{name}_{i:03d}.png"), np.hstack([frame, out]))
        seconds = len(frames) / fps
        bits = encoder.coded_bits
    return {
        "iou_min": min(ious),
        "iou_min_at": int(np.argmin(ious)),
        "iou_mean": float(np.mean(ious)),
        "face": float(np.nanmean(face)),
        "head": float(np.nanmean(head)),
        "body_kbps": bits.get(BODY, 0.0) / seconds / 1000,
        "frame_kbps": sum(bits.values()) / seconds / 1000,
        "refresh_kbps": 0.0
        if encoder.refresh is None
        else encoder.refresh.bytes * 8 / seconds / 1000,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--input", action="append", required=True)
    parser.add_argument("--motion", choices=("lean", "closer", "shift", "none"), default="lean")
    parser.add_argument("--frames", type=int, default=90)
    parser.add_argument("--no-body", action="store_true")
    parser.add_argument("--no-refresh", action="store_true")
    parser.add_argument("--pictures", type=Path)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    body = "off" if args.no_body else "followed"
    print(f"motion {args.motion}, body {body}, refreshes {'off' if args.no_refresh else 'on'}")
    for path in args.input:
        frames, fps = read(path, args.frames)
        frames = moved(frames, args.motion, fps)
        name = f"{Path(path).stem}_{args.motion}"
        r = run(frames, fps, not args.no_body, not args.no_refresh, args.pictures, name)
        print(
            f"{Path(path).name}: silhouette IoU min {r['iou_min']:.3f} (frame {r['iou_min_at']})"
            f", mean {r['iou_mean']:.3f}; face SSIM {r['face']:.4f}, head {r['head']:.4f}; "
            f"body {r['body_kbps']:.2f} kbit/s of {r['frame_kbps']:.2f} coded; "
            f"refreshes {r['refresh_kbps']:.2f} kbit/s"
        )


if __name__ == "__main__":
    main()
