"""Jitter and lag of the landmark smoother, on the bundled clip (against its truth) and on
real footage (against the raw tracker).

Usage: python benchmarks/bench_smoothing.py [--footage DIR] [--grid]

Each clip is tracked once (raw landmarks; the tracker's crops never depend on the
smoother), then smoothed offline with ``facewire.sender.smoothing.LandmarkSmoother``, which is what
``LandmarkTracker(smoother=...)`` returns frame by frame.

Bundled clip (rendered, every rig marker's true position known per frame; visible markers):
  error   RMS distance to the truth, px
  jitter  RMS frame-to-frame change of the error, px (the truth moves smoothly, so what
          changes in the error from one frame to the next is noise)
  lag     time shift (frames) that best aligns the landmarks with the truth: the landmarks at
          t fit the truth at t - lag
  blink   the lid gap (upper to lower lid marker, both eyes) at its smallest round each of the
          clip's five blinks, mean; what smoothing takes off a fast, short movement
Real clips (no truth), in % of the inter-ocular distance (outer eye corners):
  jitter  RMS second difference of the points over time (acceleration: noise, since a head
          barely accelerates between two frames)
  lag     as above, but against the raw landmarks, over the frames where the face moves
          fastest (top 10 % of speed)
  fast    95th percentile distance to the raw landmarks in those fast frames
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from facewire.sender.capture import VideoSource, demo_clip_path
from facewire.sender.landmarks import LandmarkTracker
from facewire.sender.smoothing import BETA, D_CUTOFF_HZ, MIN_CUTOFF_HZ, LandmarkSmoother

TRUTH = Path(__file__).resolve().parent.parent / "sender" / "data" / "demo_clip_truth.npz"
REAL_CLIPS = ("akiyo_cif", "carphone_qcif", "foreman_cif_first180", "mother_daughter_cif")
EYES = (33, 263)
SHIFTS = np.linspace(-6.0, 6.0, 241)


def track(path: Path) -> tuple[np.ndarray, np.ndarray, float]:
    """(n, 468, 3) raw landmarks (NaN where untracked), (n,) tracked flags, fps."""
    tracker = LandmarkTracker()
    out, ok = [], []
    with VideoSource(path) as video:
        for frame in video.frames():
            lm = tracker.track(frame.image)
            ok.append(lm is not None)
            out.append(lm.points if lm is not None else np.full((468, 3), np.nan))
        fps = video.fps
    return np.asarray(out), np.asarray(ok), fps


def smooth(
    raw: np.ndarray, ok: np.ndarray, fps: float, min_cutoff: float, beta: float, d_cutoff: float
) -> np.ndarray:
    s = LandmarkSmoother(min_cutoff=min_cutoff, beta=beta, d_cutoff=d_cutoff, fps=fps)
    out = raw.copy()
    for i in range(len(raw)):
        if not ok[i]:
            s.reset()
            continue
        out[i] = s(raw[i], i / fps)
    return out


def shifted(x: np.ndarray, shift: float) -> np.ndarray:
    """x(t - shift) by linear interpolation along axis 0 (edges held)."""
    n = len(x)
    t = np.arange(n) - shift
    i0 = np.clip(np.floor(t).astype(int), 0, n - 1)
    i1 = np.clip(i0 + 1, 0, n - 1)
    w = (t - np.floor(t)).reshape(-1, *([1] * (x.ndim - 1)))
    return (1 - w) * x[i0] + w * x[i1]


def best_lag(signal: np.ndarray, reference: np.ndarray, frames: np.ndarray) -> float:
    """Shift (frames) of ``reference`` that fits ``signal`` best on ``frames``."""
    errs = []
    for sh in SHIFTS:
        d = (signal - shifted(reference, sh))[frames]
        errs.append(np.nanmean(d**2))
    return float(SHIFTS[int(np.nanargmin(errs))])


def clip_truth_metrics(pts: np.ndarray, truth: np.lib.npyio.NpzFile) -> tuple[float, float, float]:
    v = truth["marker_vertices"]
    xy = pts[:, v, :2]
    true = truth["marker_xy"]
    vis = truth["marker_visible"][:, :, None]
    err = np.where(vis, xy - true, np.nan)
    rms = float(np.sqrt(np.nanmean((err**2).sum(axis=2))))
    derr = np.diff(err, axis=0)
    jitter = float(np.sqrt(np.nanmean((derr**2).sum(axis=2))))
    moving = np.arange(30, len(pts))  # frames 0-30 are still
    lag = best_lag(np.where(vis, xy, np.nan), true, moving)
    return rms, jitter, lag


LIDS = ((159, 145), (386, 374))


def blink_gap(xy: np.ndarray, blinks: np.ndarray) -> float:
    """Mean over blinks of the smallest lid gap (px) within 4 frames of each; xy (n, k, 2)
    indexed by mesh vertex."""
    gaps = sum(np.linalg.norm(xy[:, u] - xy[:, lo], axis=1) for u, lo in LIDS) / len(LIDS)
    return float(np.mean([np.nanmin(gaps[b - 4 : b + 5]) for b in blinks]))


def real_metrics(pts: np.ndarray, raw: np.ndarray) -> tuple[float, float, float]:
    iod = np.linalg.norm(raw[:, EYES[0], :2] - raw[:, EYES[1], :2], axis=1)
    scale = np.nanmedian(iod)
    xy = pts[:, :, :2] / scale
    acc = xy[2:] - 2 * xy[1:-1] + xy[:-2]
    jitter = float(np.sqrt(np.nanmean((acc**2).sum(axis=2)))) * 100
    rxy = raw[:, :, :2] / scale
    step = np.linalg.norm(np.diff(rxy, axis=0), axis=2)
    # Untracked frames have no speed (NaN) and take no part.
    tracked = np.isfinite(step).all(axis=1)
    mean_step = np.full(len(step), np.nan)
    mean_step[tracked] = step[tracked].mean(axis=1)
    speed = np.concatenate([[0.0], mean_step])
    fast = np.flatnonzero(speed >= np.nanpercentile(speed, 90))
    fast = fast[(fast > 3) & (fast < len(pts) - 3)]
    lag = best_lag(xy, rxy, fast)
    dev = np.linalg.norm(xy[fast] - rxy[fast], axis=2)
    return jitter, lag, float(np.nanpercentile(dev, 95)) * 100


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--footage", default="/work/footage", help="folder with the real clips")
    ap.add_argument("--grid", action="store_true", help="also try other settings")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    settings: list[tuple[float, float, float] | None] = [None, (MIN_CUTOFF_HZ, BETA, D_CUTOFF_HZ)]
    if args.grid:
        settings += [
            (m, b, d) for d in (1.0, 5.0) for m in (0.5, 1.0, 2.0) for b in (0.5, 1.5, 3.0, 5.0)
        ]
        settings = list(dict.fromkeys(settings))

    clip_raw, clip_ok, clip_fps = track(demo_clip_path())
    truth = np.load(TRUTH)
    real = {}
    for name in REAL_CLIPS:
        path = Path(args.footage) / f"{name}.avi"
        if path.is_file():
            real[name] = track(path)
        else:
            print(f"(no {path}: skipped)")

    truth_xy = np.full((len(clip_raw), 468, 2), np.nan)
    truth_xy[:, truth["marker_vertices"]] = truth["marker_xy"]
    blinks = truth["blink_frames"]
    print(f"bundled clip, lid gap at the blinks: truth {blink_gap(truth_xy, blinks):.1f} px")
    head = f"{'setting':<22}| bundled clip: error jitter  lag blink |"
    head += "".join(f" {n[:14]:>14}: jitter  lag  fast |" for n in real)
    print(head)
    for st in settings:
        label = "raw" if st is None else f"fc {st[0]:g} b {st[1]:g} dc {st[2]:g}"
        pts = clip_raw if st is None else smooth(clip_raw, clip_ok, clip_fps, *st)
        e, j, lag = clip_truth_metrics(pts, truth)
        gap = blink_gap(pts[:, :, :2], blinks)
        row = f"{label:<22}|        {e:5.2f}  {j:5.2f} {lag:+4.2f} {gap:5.1f} |"
        for raw, ok, fps in real.values():
            p = raw if st is None else smooth(raw, ok, fps, *st)
            rj, rl, rf = real_metrics(p, raw)
            row += f" {'':>14}  {rj:5.2f} {rl:+4.2f} {rf:5.2f} |"
        print(row)
    print("bundled clip: px; real clips: % of inter-ocular distance; lag in frames (+ = late)")


if __name__ == "__main__":
    main()
