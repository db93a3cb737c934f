"""REM patches: what they cost and what they buy, on a clip (both ends in one process).

Usage:
  PYOPENGL_PLATFORM=egl python benchmarks/bench_rem.py [--input CLIP ...] [--frames N]
      [--no-adapt] [--budget KBPS] [--geometry-kbps KBPS] [--crops DIR --at F,F,...]
      [--video DIR]
  python benchmarks/bench_rem.py --codecs [--input CLIP ...]

Each clip is sent twice through the real encoder and decoder (packets as bytes, no sockets,
frames stamped at the clip's frame rate): without REM patches and with them. Every frame is
rebuilt (a frame without a packet holds the last picture, as the receive loop does) and
scored against the input with facewire.quality (luma SSIM and PSNR) in regions made from the
input's own landmarks: the face (hull of the 468 points), the eyes (hulls of the eye contours
grown to take in the lids) and the mouth (hull of the outer lip contour), the mouth also over
the frames where the input's mouth is open. Printed per run: those scores, the REM payload in
kbit/s with the patches per region, geometry kbit/s, and each end's time per frame (median;
the sender: track + fit + code + REM; the receiver: decode + patches + reconstruct).

On the bundled clip the lid gap at the scripted blinks is measured in the pictures, from the
clip's own lid markers (blue dots drawn on the lids: their centres along the line from the
lower to the upper lid's true position), in the input, in the output without and with REM,
against the truth file's marker positions.

``--crops DIR --at F,...`` writes, for those frames, the eyes and the mouth of the input, the
output without REM and the output with REM side by side (PNG, enlarged). ``--video DIR``
writes each run's output as MP4.

``--codecs`` compares ways of coding a patch, on patches cut from the clip as the sender cuts
them: JPEG and WebP at several qualities and at full or half size (bytes, PSNR), and an
appearance basis (PCA of the patches of the first two seconds, k coefficients per patch:
PSNR on the rest, and the basis' size), against one learnt on the whole clip.
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from facewire.loopback import Loopback  # noqa: E402
from facewire.models.rig import load_rig  # noqa: E402
from facewire.protocol.packets import RemPatch  # noqa: E402
from facewire.quality import face_polygon, frame_scores, polygon_mask  # noqa: E402
from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path  # noqa: E402
from facewire.sender.encoder import FaceEncoder  # noqa: E402
from facewire.sender.landmarks import LandmarkTracker  # noqa: E402
from facewire.sender.rate_cap import GEOMETRY_KBPS  # noqa: E402

RIGHT_EYE = (33, 7, 163, 144, 145, 153, 154, 155, 133, 173, 157, 158, 159, 160, 161, 246)
LEFT_EYE = (263, 249, 390, 373, 374, 380, 381, 382, 362, 398, 384, 385, 386, 387, 388, 466)
#: Eye hulls grown about their centre by this factor (the lids and lashes).
EYE_GROW = 1.6
#: The input's mouth is open when its inner lips (13, 14) are this far apart, per mouth width.
MOUTH_OPEN = 0.08
REGIONS = ("face", "eyes", "mouth", "mouth open")


def _grown(points: np.ndarray, factor: float) -> np.ndarray:
    hull = cv2.convexHull(points.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    centre = hull.mean(axis=0)
    return centre + factor * (hull - centre)


def masks(points: np.ndarray, shape: tuple[int, ...]) -> dict[str, np.ndarray]:
    """Face, eyes and mouth masks from one frame's landmarks ((468, 2+) pixels)."""
    xy = points[:, :2]
    eyes = polygon_mask(_grown(xy[list(RIGHT_EYE)], EYE_GROW), shape) | polygon_mask(
        _grown(xy[list(LEFT_EYE)], EYE_GROW), shape
    )
    lips = list(load_rig().lips.contours[0])
    mouth = polygon_mask(_grown(xy[lips], 1.0), shape)
    out = {"face": polygon_mask(face_polygon(points), shape), "eyes": eyes, "mouth": mouth}
    width = np.linalg.norm(xy[291] - xy[61])
    if np.linalg.norm(xy[13] - xy[14]) > MOUTH_OPEN * width:
        out["mouth open"] = mouth
    return out


@dataclass
class Run:
    """One call's pictures and figures."""

    outputs: list[np.ndarray] = field(default_factory=list)
    rem_bytes: int = 0
    geometry_bytes: int = 0
    patches: dict[str, int] = field(default_factory=dict)
    send_s: list[float] = field(default_factory=list)
    receive_s: list[float] = field(default_factory=list)
    receiver_counts: dict[str, object] = field(default_factory=dict)
    # CPU seconds spent on REM alone per frame: the sender's cut, detection and coding; the
    # receiver's patch decoding, adaptation, merging and texture upload.
    rem_send_s: list[float] = field(default_factory=list)
    rem_receive_s: list[float] = field(default_factory=list)


def _timed(owner: object, name: str, spent: list[float]) -> None:
    """Wrap ``owner.name`` so each call adds its CPU time (process_time) to ``spent[-1]``."""
    inner = getattr(owner, name)

    def wrapper(*args: object, **kwargs: object) -> object:
        t0 = time.process_time()
        try:
            return inner(*args, **kwargs)
        finally:
            spent[-1] += time.process_time() - t0

    setattr(owner, name, wrapper)


def call(
    frames: list[CapturedFrame],
    size: tuple[int, int],
    fps: float,
    rem: bool,
    adapt: bool = True,
    budget_kbps: float | None = None,
    regions: tuple[str, ...] | None = None,
    geometry_kbps: float = GEOMETRY_KBPS,
) -> Run:
    """Both ends over ``frames``; every frame rebuilt (``geometry_kbps`` 0: no rate cap)."""
    encoder = FaceEncoder(size[0], size[1], fps, rem=rem, geometry_kbps=geometry_kbps or None)
    run = Run()
    with Loopback(encoder, frames[0]) as both:
        decoder = both.decoder
        if encoder.rem is not None and budget_kbps is not None:
            encoder.rem.set_budget(budget_kbps)
        if encoder.rem is not None and regions is not None:
            encoder.rem.regions = regions
        if decoder.rem is not None:
            decoder.rem.adapt_colour = adapt
        if encoder.rem is not None and decoder.rem is not None:
            _timed(encoder.rem, "changed", run.rem_send_s)
            _timed(encoder.rem, "keyframe", run.rem_send_s)
            _timed(decoder, "add_patch", run.rem_receive_s)
            _timed(decoder.rem, "due", run.rem_receive_s)
            _timed(decoder.renderer, "set_texture", run.rem_receive_s)
        last = None
        for frame in frames:
            run.rem_send_s.append(0.0)
            run.rem_receive_s.append(0.0)
            t0 = time.perf_counter()
            sent = both.send(frame)
            run.send_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            for data, packet in zip(sent, both.receive(sent), strict=True):
                if isinstance(packet, RemPatch):
                    run.rem_bytes += len(data)
                    run.patches[packet.region] = run.patches.get(packet.region, 0) + 1
                else:
                    last = both.picture()
                    run.geometry_bytes += len(data)
            run.receive_s.append(time.perf_counter() - t0)
            assert last is not None
            run.outputs.append(last)
        run.receiver_counts = decoder.rem_counts()
    return run


def scores(
    inputs: list[np.ndarray], outputs: list[np.ndarray], points: list[np.ndarray | None]
) -> dict[str, tuple[float, float]]:
    """Mean (SSIM, PSNR dB) per region over the frames where it exists."""
    acc: dict[str, list[tuple[float, float]]] = {r: [] for r in REGIONS}
    for ref, out, p in zip(inputs, outputs, points, strict=True):
        if p is None:
            continue
        for region, value in frame_scores(ref, out, masks(p, ref.shape)).items():
            acc[region].append(value)
    return {
        r: (
            float(np.mean([s for s, _ in v])) if v else float("nan"),
            float(np.mean([min(d, 100.0) for _, d in v])) if v else float("nan"),
        )
        for r, v in acc.items()
    }


def lid_gap(image: np.ndarray, upper: np.ndarray, lower: np.ndarray, open_gap: float) -> float:
    """Distance between the two lid markers' blue dots near their true positions, px.

    The blue of the dots (BGR 230, 80, 0) is looked for within ``open_gap`` / 2 + 5 px of
    the two true positions' midpoint. The blue pixels are split in two along their main
    direction (weighted 1-D two-means from its ends): two dots apart, or one blob where
    they touch. The distance of the two halves' weighted centres is the gap.
    """
    centre = (upper + lower) / 2
    radius = open_gap / 2 + 5
    x0, y0 = np.floor(centre - radius).astype(int)
    x1, y1 = np.ceil(centre + radius).astype(int)
    h, w = image.shape[:2]
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)
    patch = image[y0 : y1 + 1, x0 : x1 + 1].astype(np.float32)
    blue = patch[:, :, 0] - np.maximum(patch[:, :, 1], patch[:, :, 2])
    ys, xs = np.mgrid[y0 : y1 + 1, x0 : x1 + 1]
    keep = (blue > 60) & ((xs - centre[0]) ** 2 + (ys - centre[1]) ** 2 <= radius**2)
    if keep.sum() < 2:
        return float("nan")
    points = np.column_stack([xs[keep], ys[keep]]).astype(np.float64)
    weight = blue[keep].astype(np.float64)
    mean = np.average(points, axis=0, weights=weight)
    cov = np.cov((points - mean).T, aweights=weight)
    axis = np.linalg.eigh(cov)[1][:, -1]
    t = (points - mean) @ axis
    a, b = t.min(), t.max()
    near_a = np.abs(t - a) <= np.abs(t - b)
    for _ in range(20):
        near_a = np.abs(t - a) <= np.abs(t - b)
        if near_a.all() or not near_a.any():
            return 0.0
        a = float(np.average(t[near_a], weights=weight[near_a]))
        b = float(np.average(t[~near_a], weights=weight[~near_a]))
    first = np.average(points[near_a], axis=0, weights=weight[near_a])
    second = np.average(points[~near_a], axis=0, weights=weight[~near_a])
    return float(np.linalg.norm(first - second))


def blink_gaps(outputs: list[np.ndarray]) -> list[float]:
    """Lid gap (mean of both eyes, from the dots) at the bundled clip's blinks."""
    truth = np.load(demo_clip_path().with_name("demo_clip_truth.npz"))
    names = truth["marker_names"].tolist()
    xy = truth["marker_xy"]
    out = []
    for f in truth["blink_frames"]:
        gaps = []
        for side in ("right", "left"):
            up, low = names.index(f"upper_lid_{side}"), names.index(f"lower_lid_{side}")
            open_gap = float(np.linalg.norm(xy[0, up] - xy[0, low]))
            gaps.append(lid_gap(outputs[f], xy[f, up], xy[f, low], open_gap))
        out.append(float(np.mean(gaps)))
    return out


def truth_blink_gaps() -> list[float]:
    truth = np.load(demo_clip_path().with_name("demo_clip_truth.npz"))
    names = truth["marker_names"].tolist()
    xy = truth["marker_xy"]
    return [
        float(
            np.mean(
                [
                    np.linalg.norm(
                        xy[f, names.index(f"upper_lid_{s}")] - xy[f, names.index(f"lower_lid_{s}")]
                    )
                    for s in ("right", "left")
                ]
            )
        )
        for f in truth["blink_frames"]
    ]


def crops(
    path: Path,
    frames: list[int],
    inputs: list[np.ndarray],
    runs: dict[str, Run],
    points: list[np.ndarray | None],
    folder: Path,
) -> None:
    """Eyes and mouth of the input and each run's output, side by side, enlarged."""
    folder.mkdir(parents=True, exist_ok=True)
    for f in frames:
        p = points[f] if f < len(points) else None
        if p is None:
            continue
        xy = p[:, :2]
        width = float(np.ptp(xy[:, 0]))
        boxes = {
            "eyes": (xy[list(RIGHT_EYE) + list(LEFT_EYE)], 0.12 * width),
            "mouth": (xy[list(load_rig().lips.contours[0])], 0.10 * width),
        }
        for part, (pts, margin) in boxes.items():
            x0, y0 = np.floor(pts.min(axis=0) - margin).astype(int)
            x1, y1 = np.ceil(pts.max(axis=0) + margin).astype(int)
            x0, y0 = max(x0, 0), max(y0, 0)
            tiles = [inputs[f][y0:y1, x0:x1]] + [r.outputs[f][y0:y1, x0:x1] for r in runs.values()]
            scale = max(1, int(round(360 / max(1, tiles[0].shape[1]))))
            row = np.hstack([np.pad(t, ((0, 0), (0, 2), (0, 0))) for t in tiles])
            big = cv2.resize(row, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
            label = "input | " + " | ".join(runs)
            cv2.putText(big, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1)
            cv2.imwrite(str(folder / f"{path.stem}_{f:03d}_{part}.png"), big)


def write_video(path: Path, outputs: list[np.ndarray], fps: float) -> None:
    h, w = outputs[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"mp4v"), fps, (w, h))
    for image in outputs:
        writer.write(image)
    writer.release()


def bench_clip(path: Path, args: argparse.Namespace) -> None:
    with VideoSource(path) as video:
        fps, size = video.fps, (video.width, video.height)
        frames = [
            CapturedFrame(f.index, f.image, round(f.index * 1e6 / fps))
            for f in video.frames(limit=args.frames)
        ]
    inputs = [f.image for f in frames]
    tracker = LandmarkTracker()
    points = [None if (t := tracker.track(img)) is None else t.points for img in inputs]
    duration = len(frames) / fps
    runs = {"no REM": call(frames, size, fps, rem=False, geometry_kbps=args.geometry_kbps)}
    runs["REM"] = call(
        frames,
        size,
        fps,
        rem=True,
        adapt=not args.no_adapt,
        budget_kbps=args.budget,
        regions=args.regions,
        geometry_kbps=args.geometry_kbps,
    )
    print(f"{path.name} ({size[0]}x{size[1]}, {len(frames)} frames):")
    print("  run     " + "  ".join(f"{r + ' SSIM/PSNR':>22}" for r in REGIONS))
    for name, run in runs.items():
        s = scores(inputs, run.outputs, points)
        cells = "  ".join(f"{s[r][0]:>13.4f} {s[r][1]:>7.2f} dB" for r in REGIONS)
        print(f"  {name:<7} {cells}")
    for name, run in runs.items():
        print(
            f"  {name}: REM {run.rem_bytes * 8 / duration / 1000:.2f} kbit/s "
            f"(patches {dict(sorted(run.patches.items()))}), geometry "
            f"{run.geometry_bytes * 8 / duration / 1000:.2f} kbit/s; sender "
            f"{1000 * np.median(run.send_s):.2f} ms, receiver "
            f"{1000 * np.median(run.receive_s):.2f} ms per frame (median), receiver p90 "
            f"{1000 * np.percentile(run.receive_s, 90):.2f} ms"
        )
    print(f"  receiver's REM counts: {runs['REM'].receiver_counts}")
    rem = runs["REM"]

    def spread(seconds: list[float]) -> str:
        ms = 1000 * np.asarray(seconds)
        return (
            f"median {np.median(ms):.2f} ms, mean {ms.mean():.2f}, p90 "
            f"{np.percentile(ms, 90):.2f}, max {ms.max():.2f}"
        )

    print(f"  REM's own CPU time per frame: sender {spread(rem.rem_send_s)}")
    print(f"    receiver {spread(rem.rem_receive_s)}")
    if path.resolve() == demo_clip_path().resolve():
        print(f"  lid gap at the blinks, truth: {np.round(truth_blink_gaps(), 1).tolist()} px")
        print(f"    input (dots): {np.round(blink_gaps(inputs), 1).tolist()}")
        for name, run in runs.items():
            print(f"    {name}: {np.round(blink_gaps(run.outputs), 1).tolist()}")
    if args.crops:
        crops(path, args.at, inputs, runs, points, args.crops)
    if args.video:
        args.video.mkdir(parents=True, exist_ok=True)
        for name, run in runs.items():
            write_video(args.video / f"{path.stem}_{name.replace(' ', '_')}.mp4", run.outputs, fps)


# --- patch coding ---------------------------------------------------------------------------


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return 10 * np.log10(255.0**2 / max(mse, 1e-9))


def _coded(image: np.ndarray, codec: str, quality: int, scale: float) -> tuple[int, np.ndarray]:
    h, w = image.shape[:2]
    small = image
    if scale != 1:
        size = (max(2, round(w * scale)), max(2, round(h * scale)))
        small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    if codec == "jpeg":
        params = [cv2.IMWRITE_JPEG_QUALITY, quality, cv2.IMWRITE_JPEG_OPTIMIZE, 1]
        ok, buf = cv2.imencode(".jpg", small, params)
    else:
        ok, buf = cv2.imencode(".webp", small, [cv2.IMWRITE_WEBP_QUALITY, quality])
    assert ok
    out = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    assert out is not None
    if scale != 1:
        out = cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR)
    return len(buf), out


def patches_of(path: Path, frames: int | None) -> dict[str, np.ndarray]:
    """Every frame's patch of every region, cut as the sender cuts them."""
    with VideoSource(path) as video:
        fps = video.fps
        encoder = FaceEncoder(video.width, video.height, fps)
        out: dict[str, list[np.ndarray]] = {}
        started = False
        for f in video.frames(limit=frames):
            frame = CapturedFrame(f.index, f.image, round(f.index * 1e6 / fps))
            if not started:
                started = encoder.start(frame) is not None
                continue
            result = encoder.analyse(frame.image)
            encoder.encode_analysed(frame, result)
            encoder.take_patches()
            rem = encoder.rem
            assert rem is not None and encoder._last_values is not None
            ext = rem.layout.vertices(encoder.rebuilt_vertices(encoder._last_values))
            for name in rem.regions:
                out.setdefault(name, []).append(rem.cut(frame.image, ext, name)[0])
    return {k: np.array(v) for k, v in out.items()}


def bench_codecs(path: Path, frames: int | None) -> None:
    cut = patches_of(path, frames)
    print(f"{path.name}:")
    for region in ("eye_right", "mouth_interior"):
        stack = cut[region]
        sample = stack[::10]
        print(f"  {region}, {stack.shape[2]}x{stack.shape[1]} texels:")
        for codec in ("jpeg", "webp"):
            for scale in (1.0, 0.5):
                cells = []
                for q in (10, 30, 50, 75):
                    coded = [_coded(p, codec, q, scale) for p in sample]
                    nbytes = np.mean([c[0] for c in coded])
                    db = np.mean([_psnr(p, c[1]) for p, c in zip(sample, coded, strict=True)])
                    cells.append(f"q{q} {nbytes:.0f} B {db:.1f} dB")
                print(f"    {codec} at {scale:g} size: " + ", ".join(cells))
        x = stack.reshape(len(stack), -1).astype(np.float64)
        learn = int(2 * 30)
        for label, train in (("first 2 s", x[:learn]), ("whole clip", x)):
            mean = train.mean(axis=0)
            _, _, vt = np.linalg.svd(train - mean, full_matrices=False)
            cells = []
            for k in (4, 8, 16):
                basis = vt[:k]
                c = (x[learn:] - mean) @ basis.T
                step = np.abs((train - mean) @ basis.T).max(axis=0) / 127 + 1e-9
                rebuilt = np.clip(np.round(c / step) * step @ basis + mean, 0, 255)
                db = np.mean([_psnr(a, b) for a, b in zip(x[learn:], rebuilt, strict=True)])
                blink = ""
                if path.resolve() == demo_clip_path().resolve() and region in ("eye_right",):
                    # The clip's first blink (frames 98-102; patch i is frame i + 1).
                    at = [f - 1 - learn for f in range(98, 103)]
                    worst = min(_psnr(x[learn + i], rebuilt[i]) for i in at)
                    webp = min(
                        _psnr(stack[learn + i], _coded(stack[learn + i], "webp", 10, 1)[1])
                        for i in at
                    )
                    blink = f" (first blink: {worst:.1f} dB; WebP q10 there {webp:.1f})"
                basis_png = len(
                    cv2.imencode(".png", np.clip(basis * 127 + 128, 0, 255).astype(np.uint8))[1]
                )
                cells.append(
                    f"k={k}: {db:.1f} dB{blink}, {k} B a patch, basis {basis_png / 1024:.0f} KiB"
                )
            print(f"    PCA learnt on the {label}: " + "; ".join(cells))


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--input", type=Path, action="append")
    parser.add_argument("--frames", type=int)
    parser.add_argument("--no-adapt", action="store_true", help="paste without Eq. 2")
    parser.add_argument("--budget", type=float, help="REM kbit/s (default: the sender's)")
    parser.add_argument(
        "--geometry-kbps",
        type=float,
        default=GEOMETRY_KBPS,
        help="the sender's rate cap on frame packets (default its own; 0: none)",
    )
    parser.add_argument(
        "--regions",
        type=lambda s: tuple(s.split(",")),
        help="regions to send, comma-separated (default: the sender's)",
    )
    parser.add_argument("--crops", type=Path)
    parser.add_argument("--at", type=lambda s: [int(x) for x in s.split(",")], default=[])
    parser.add_argument("--video", type=Path)
    parser.add_argument("--codecs", action="store_true")
    args = parser.parse_args()
    cv2.setNumThreads(1)
    for path in args.input or [demo_clip_path()]:
        if args.codecs:
            bench_codecs(path, args.frames)
        else:
            bench_clip(path, args)


if __name__ == "__main__":
    main()
