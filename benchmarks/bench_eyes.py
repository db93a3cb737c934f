"""Lids with and without the eye model (sender.eyes): lid gaps, error against truth, time.

Usage: python benchmarks/bench_eyes.py [CLIP ...]   (default: the bundled clip)

Each clip is tracked twice, by ``LandmarkTracker(refine_eyes=False)`` and by the default
tracker, with OpenCV on one thread. Printed per clip: the lid gap (upper to lower lid at the
middle of each eye, mean of both eyes, px) at the first frame and its lowest values over the
clip, and the tracker's median time per frame. For the bundled clip also the gap at the
scripted blinks and the lid markers' median error against the clip's truth.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from facewire.sender.capture import VideoSource, demo_clip_path
from facewire.sender.landmarks import LandmarkTracker

LID_MARKERS = ("upper_lid_right", "lower_lid_right", "upper_lid_left", "lower_lid_left")


def lid_gap(points: np.ndarray) -> float:
    """Mean over both eyes of the upper-to-lower lid distance at the eye's middle, px."""
    pairs = ((159, 145), (386, 374))
    return float(np.mean([np.linalg.norm(points[a, :2] - points[b, :2]) for a, b in pairs]))


def track(path: Path, refine: bool) -> tuple[np.ndarray, list[float]]:
    """(frames, 468, 3) landmarks (NaN where no face) and the time of each frame, s."""
    tracker = LandmarkTracker(refine_eyes=refine)
    points, times = [], []
    with VideoSource(path) as video:
        for frame in video.frames():
            t0 = time.perf_counter()
            found = tracker.track(frame.image)
            times.append(time.perf_counter() - t0)
            points.append(np.full((468, 3), np.nan) if found is None else found.points)
    return np.array(points), times[1:]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("clips", nargs="*", type=Path)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    for path in args.clips or [demo_clip_path()]:
        runs = {refine: track(path, refine) for refine in (False, True)}
        print(f"{path.name}:")
        for refine, (points, times) in runs.items():
            gaps = np.array([lid_gap(p) for p in points])
            low = np.sort(gaps[np.isfinite(gaps)])[:5]
            print(
                f"  {'with' if refine else 'without'} the eye model: lid gap at frame 0 "
                f"{gaps[0]:.1f} px, lowest {np.round(low, 1).tolist()}; "
                f"tracker {1000 * np.median(times):.1f} ms per frame"
            )
            if path.resolve() == demo_clip_path().resolve():
                truth = np.load(path.with_name("demo_clip_truth.npz"))
                names = truth["marker_names"].tolist()
                cols = [names.index(n) for n in LID_MARKERS]
                vertices = truth["marker_vertices"][cols]
                n = min(len(points), len(truth["marker_xy"]))
                err = np.linalg.norm(
                    points[:n, vertices, :2] - truth["marker_xy"][:n, cols], axis=2
                )
                blinks = truth["blink_frames"]
                print(
                    f"    at the blinks (truth 4.1 px): {np.round(gaps[blinks], 1).tolist()}; "
                    f"lid markers' median error px ({', '.join(LID_MARKERS)}): "
                    f"{np.round(np.median(err, axis=0), 2).tolist()}"
                )


if __name__ == "__main__":
    main()
