"""Time the face detector and steady-state landmark tracking at 640x480 on one thread.

Usage: python benchmarks/bench_tracker.py [--frames N] [--threads T]

The astronaut fixture is placed in a 640x480 frame and moved slowly (shift and roll per
frame), so tracking runs from the previous landmarks as it would on a live call.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from models.mesh import load_canonical
from models.pose import estimate_pose
from sender.detector import FaceDetector
from sender.landmarks import OUTPUT_LAYERS, LandmarkTracker

FIXTURE = Path(__file__).resolve().parent.parent / "tests" / "fixtures" / "astronaut_face.jpg"


def frames(n: int) -> list[np.ndarray]:
    face = cv2.imread(str(FIXTURE))
    if face is None:
        raise SystemExit(f"cannot read {FIXTURE}")
    out = []
    for k in range(n):
        phase = 2 * np.pi * k / max(n, 1)
        m = cv2.getRotationMatrix2D((210.0, 120.0), 8.0 * np.sin(phase), 1.0)
        m[:, 2] += (110 + 30 * np.sin(phase), 30 + 10 * np.cos(phase))
        out.append(cv2.warpAffine(face, m, (640, 480), borderMode=cv2.BORDER_REFLECT))
    return out


def per_frame_ms(fn, items: list[np.ndarray]) -> np.ndarray:  # type: ignore[no-untyped-def]
    times = []
    for item in items:
        t0 = time.perf_counter()
        fn(item)
        times.append(time.perf_counter() - t0)
    return 1e3 * np.asarray(times)


def report(name: str, ms: np.ndarray) -> None:
    print(
        f"{name:<28} median {np.median(ms):6.2f} ms  p90 {np.percentile(ms, 90):6.2f} ms  "
        f"mean {ms.mean():6.2f} ms  ({1e3 / np.median(ms):5.0f} fps, n={len(ms)})"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    cv2.setNumThreads(args.threads)
    print(f"OpenCV {cv2.__version__}, cv2.setNumThreads({args.threads}), 640x480 frames")

    seq = frames(args.frames)
    detector = FaceDetector()
    for f in seq[:10]:
        detector.detect(f)
    report("detector", per_frame_ms(detector.detect, seq))

    tracker = LandmarkTracker(detector=detector)
    for f in seq[:10]:
        tracker.track(f)
    lost = 0

    def track(f: np.ndarray) -> None:
        nonlocal lost
        lost += tracker.track(f) is None

    report("landmarks (steady state)", per_frame_ms(track, seq))
    print(f"frames lost: {lost}")

    net_only = per_frame_ms(lambda _: tracker.net.forward(OUTPUT_LAYERS), seq[:100])
    report("  landmark net forward only", net_only)

    canonical = load_canonical().vertices
    lm = tracker.track(seq[0])
    assert lm is not None
    pts = [lm.points] * len(seq)
    report("estimate_pose (468 points)", per_frame_ms(lambda p: estimate_pose(canonical, p), pts))


if __name__ == "__main__":
    main()
