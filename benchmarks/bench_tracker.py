"""Time the face detector and steady-state landmark tracking at 640x480 on one thread, and
measure how small a face is found.

Usage: python benchmarks/bench_tracker.py [--frames N] [--threads T] [--small] [--footage DIR]

The astronaut fixture is placed in a 640x480 frame and moved slowly (shift and roll per
frame), so tracking runs from the previous landmarks as it would on a live call.

With --small: the cost of looking for a face that is not there (whole frame plus tiles) at
several frame sizes; how often a face of 40-100 px is found in one still frame (the astronaut
on a textured background, 12 random places per size), with and without the tiled second
look; and real clips (DIR, default /work/footage) shrunk so the face is 48 or 64 px wide and
pasted into a 640x480 frame: frames tracked, and the landmarks' distance from the full-size
clip's (scaled down), in % of the inter-ocular distance.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from facewire.models.mesh import load_canonical
from facewire.models.pose import estimate_pose
from facewire.sender.detector import FaceDetector, tile_grid
from facewire.sender.landmarks import LandmarkTracker

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
    ap.add_argument("--small", action="store_true", help="also measure small faces")
    ap.add_argument("--footage", default="/work/footage", help="folder of real clips")
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

    still = np.zeros(tracker.net.input_shape[1:], np.float32)
    net_only = per_frame_ms(lambda _: tracker.net.run(still), seq[:100])
    report("  landmark net forward only", net_only)

    canonical = load_canonical().vertices
    lm = tracker.track(seq[0])
    assert lm is not None
    pts = [lm.points] * len(seq)
    report("estimate_pose (468 points)", per_frame_ms(lambda p: estimate_pose(canonical, p), pts))
    if args.small:
        small_faces(Path(args.footage))


def scenery(w: int, h: int, rng: np.random.Generator) -> np.ndarray:
    """Smooth colour blobs plus grain: a background with no face."""
    coarse = rng.integers(40, 220, (6, 8, 3), dtype=np.uint8)
    img = cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(img + rng.normal(0, 6, img.shape), 0, 255).astype(np.uint8)


def paste(canvas: np.ndarray, img: np.ndarray, scale: float, src_c: np.ndarray, dst_c: np.ndarray):  # type: ignore[no-untyped-def]
    """``canvas`` with ``img`` scaled by ``scale`` so its point ``src_c`` lands on ``dst_c``."""
    m = np.array([[scale, 0, dst_c[0] - scale * src_c[0]], [0, scale, dst_c[1] - scale * src_c[1]]])
    h, w = canvas.shape[:2]
    return cv2.warpAffine(img, m, (w, h), dst=canvas.copy(), borderMode=cv2.BORDER_TRANSPARENT)


def small_faces(footage: Path) -> None:
    rng = np.random.default_rng(0)
    print("\nlooking for a face that is not there (whole frame + tiles):")
    for w, h in [(640, 480), (1280, 720), (1920, 1080), (3840, 2160)]:
        frame = scenery(w, h, rng)
        t_full = per_frame_ms(LandmarkTracker(search_budget=None).track, [frame] * 3)
        t_budget = per_frame_ms(LandmarkTracker().track, [frame] * 20)
        print(
            f"  {w}x{h}: {len(tile_grid(w, h)):3d} tiles; one still image "
            f"{np.median(t_full):7.1f} ms; a video frame (whole frame + 4 tiles) "
            f"{np.median(t_budget):5.1f} ms"
        )

    face = cv2.imread(str(FIXTURE))
    assert face is not None
    ref = LandmarkTracker()
    ref.track(face)
    lm = ref.track(face)
    assert lm is not None
    c0, w0 = lm.points[:, :2].mean(axis=0), float(np.ptp(lm.points[:, 0]))
    print("\nastronaut in one still frame, found / tried (12 places per size):")
    for w, h in [(640, 480), (1920, 1080)]:
        row = f"  {w}x{h}:"
        for width in (40, 48, 56, 64, 80, 100):
            found = {True: 0, False: 0}
            for _ in range(12):
                dst = rng.uniform([width, width], [w - width, h - width])
                img = paste(scenery(w, h, rng), face, width / w0, c0, dst)
                for tiles in (True, False):
                    t = LandmarkTracker(min_face=48.0 if tiles else None, search_budget=None)
                    got = t.track(img)
                    near = got is not None and bool(
                        np.linalg.norm(got.points[:, :2].mean(axis=0) - dst) < 0.3 * width
                    )
                    found[tiles] += int(near)
            row += f"  {width} px {found[True]:2d} ({found[False]:2d})"
        print(row + "   (in brackets: without the tiled second look)")

    print("\nreal clips shrunk into a 640x480 frame (first 90 frames):")
    for name in ("carphone_qcif", "akiyo_cif", "foreman_cif_first180", "mother_daughter_cif"):
        path = footage / f"{name}.avi"
        if not path.is_file():
            print(f"  {name}: not found, skipped")
            continue
        cap = cv2.VideoCapture(str(path))
        clip: list[np.ndarray] = []
        while len(clip) < 90:
            ok, f = cap.read()
            if not ok:
                break
            clip.append(f)
        cap.release()
        reference = LandmarkTracker()
        full = [reference.track(f) for f in clip]
        first = next(x for x in full if x is not None)
        width0 = float(np.ptp(first.points[:, 0]))
        centre0 = first.points[:, :2].mean(axis=0)
        for width in (48, 64):
            s = width / width0
            dst = np.array([100.0, 400.0])  # in the last row of tiles: found last
            bg = scenery(640, 480, np.random.default_rng(1))
            t = LandmarkTracker()
            tracked, errs = 0, []
            first_found = None
            for i, f in enumerate(clip):
                got = t.track(paste(bg, f, s, centre0, dst))
                if got is None:
                    continue
                tracked += 1
                first_found = i if first_found is None else first_found
                ref_lm = full[i]
                if ref_lm is not None:
                    want = (ref_lm.points[:, :2] - centre0) * s + dst
                    iod = np.linalg.norm(want[33] - want[263])
                    errs.append(np.linalg.norm(got.points[:, :2] - want, axis=1).mean() / iod)
            print(
                f"  {name:<22} face {width} px: {tracked}/{len(clip)} frames tracked, first at "
                f"frame {first_found}; mean distance from the full-size landmarks "
                f"{100 * np.median(errs):.1f} % IOD (median over frames)"
            )


if __name__ == "__main__":
    main()
