"""Coloured markers (sender.markers, sender.lift) against the bundled clip's truth, and the
rebuilt face from the markers next to the landmark tracker's.

Usage: PYOPENGL_PLATFORM=egl python benchmarks/bench_markers.py [--threads T]
       python benchmarks/bench_markers.py --stickers CLIP [--stickers CLIP ...] [--frames N]

Printed:
- 2D markers: error against the truth over every marker the clip drew (px), markers missed,
  the tracker's time per frame; and the same with 11 markers painted out over frames 60-99
  and all of them over 120-149 (how many frames until every marker is back, and how far
  each is from its own truth then: a marker under another's name would be 8 px or more off).
- 3D: the lifted marker displacements against the truth's, in mm, split into across the
  image and depth (camera axes), from the tracked markers on the session mesh (its model
  space mapped onto the truth's by a similarity), and from the truth's exact 2D positions
  on the truth's own mesh (what ray casting itself gets right).
- The rebuilt face, both trackers through the whole sender (smoothing, the 16-coefficient
  wire basis, quantisation), its packets decoded by the receiver's decoder: all 468 vertices
  and the markers against the truth (px), the lids at the scripted blinks, geometry bit
  rate, sender time per frame; for the markers also the wires fitted before the basis.
- Ray casting time: the BVH against every triangle, for the rig's 29 rays.
- With ``--stickers``: real footage with the markers drawn on it (see :func:`stickers_on`).

Times are medians on one OpenCV thread; the machine's load average is printed with them.
"""

from __future__ import annotations

import argparse
import os
import time
from typing import Any

import cv2
import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from facewire.loopback import Loopback  # noqa: E402
from facewire.models.mesh import load_canonical  # noqa: E402
from facewire.models.pose import Pose, estimate_pose  # noqa: E402
from facewire.models.raycast import RayCaster, orthographic_rays  # noqa: E402
from facewire.models.rig import load_rig  # noqa: E402
from facewire.models.wires import WireDeformer  # noqa: E402
from facewire.protocol.packets import RemPatch  # noqa: E402
from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path  # noqa: E402
from facewire.sender.encoder import FaceEncoder  # noqa: E402
from facewire.sender.lift import MarkerFaceTracker, MarkerLifter  # noqa: E402
from facewire.sender.markers import SEEN, Markers, MarkerTracker  # noqa: E402

GROUP = (
    "brow_inner_right brow_mid_right brow_outer_right upper_lid_right lower_lid_right "
    "mouth_right lip_top lip_bottom mouth_left nose_tip eye_outer_right"
).split()
GROUP_FRAMES = range(60, 100)
ALL_FRAMES = range(120, 150)
LIDS = ((159, 145), (386, 374))


def _stats(a: np.ndarray) -> str:
    return f"median {np.median(a):.2f}, p90 {np.percentile(a, 90):.2f}, max {a.max():.2f}"


def _ms(t: list[float]) -> str:
    m = 1000 * float(np.median(t))
    return f"{m:.2f} ms ({1000 / m:.0f} fps), p90 {1000 * np.percentile(t, 90):.2f} ms"


def paint_out(image: np.ndarray, xy: np.ndarray, radius: float = 7.0) -> None:
    """Cover a marker with the median colour of the skin round it."""
    x, y = xy
    yy, xx = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    d = np.hypot(xx - x, yy - y)
    image[d <= radius] = np.median(image[(d > radius + 2) & (d < radius + 6)], axis=0)


def markers_2d(frames: list[np.ndarray], truth: dict[str, Any]) -> None:
    tracker = MarkerTracker()
    err, missed, times = [], 0, []
    for i, image in enumerate(frames):
        t0 = time.perf_counter()
        found = tracker.track(image)
        times.append(time.perf_counter() - t0)
        assert found is not None
        visible = truth["marker_visible"][i]
        e = np.linalg.norm(found.xy - truth["marker_xy"][i], axis=1)
        err.append(e[visible & found.seen])
        missed += int((visible & ~found.seen).sum())
    e = np.concatenate(err)
    print(f"2D markers, bundled clip ({len(frames)} frames, {len(e)} marker positions):")
    print(f"  error px: {_stats(e)}, p99 {np.percentile(e, 99):.2f}; missed {missed}")
    print(f"  tracker per frame: {_ms(times[1:])}")

    names = [str(n) for n in truth["marker_names"]]
    group = [names.index(n) for n in GROUP]
    tracker = MarkerTracker()
    back: dict[str, tuple[int, float]] = {}
    for i, image in enumerate(frames[:160]):
        image = image.copy()
        if i in GROUP_FRAMES:
            for g in group:
                paint_out(image, truth["marker_xy"][i][g])
        if i in ALL_FRAMES:
            for xy in truth["marker_xy"][i]:
                paint_out(image, xy)
        found = tracker.track(image)
        for label, end in (
            ("11 markers hidden over frames 60-99", 100),
            ("all hidden 120-149", 150),
        ):
            if found is None or label in back or i < end:
                continue
            visible = truth["marker_visible"][i]
            if (found.seen | ~visible).all():
                e = np.linalg.norm(found.xy - truth["marker_xy"][i], axis=1)[visible]
                back[label] = (i - end, float(e.max()))
    for label, (late, worst) in back.items():
        print(
            f"  {label}: every marker back {late} frame(s) after, "
            f"each within {worst:.2f} px of its own truth"
        )


def lift_3d(frames: list[np.ndarray], truth: dict[str, Any]) -> None:
    rig = load_rig()
    person = truth["person_vertices"]
    truth_wires = WireDeformer.from_rig(person, rig)
    vertices = truth["marker_vertices"]
    canonical = load_canonical()

    def camera_split(d: np.ndarray, rotation: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        c = d @ rotation.T
        return np.linalg.norm(c[:, :2], axis=1) * 10, np.abs(c[:, 2]) * 10  # mm

    # Tracked markers on the session mesh (as the sender runs them).
    tracker = MarkerFaceTracker()
    encoder = FaceEncoder(640, 480, float(truth["fps"]), tracker=tracker)
    encoder.start(CapturedFrame(0, frames[0], 0))
    assert encoder.session is not None and tracker.lifter is not None
    mesh = encoder.session.mesh.vertices
    to_mesh = estimate_pose(person, mesh)  # truth model space -> session model space
    total, across, depth, moving = [], [], [], []
    lift_t = []
    for i, image in enumerate(frames[1:], start=1):
        markers = tracker.markers.track(image)
        assert markers is not None
        t0 = time.perf_counter()
        fit = tracker.lifter.lift(markers)
        lift_t.append(time.perf_counter() - t0)
        true = to_mesh.scale * (truth_wires.deform(truth["wire_params"][i]) - person)[vertices]
        true = true @ to_mesh.rotation.T
        d = fit.marker_displacement - true
        a, z = camera_split(d, fit.pose.rotation)
        total.append(np.linalg.norm(d, axis=1) * 10)
        across.append(a)
        depth.append(z)
        moving.append(np.linalg.norm(true, axis=1) * 10)
    t, a, z, m = (np.concatenate(x) for x in (total, across, depth, moving))
    print("3D marker displacements, lifted from the tracked markers (mm):")
    print(f"  true displacements: {_stats(m)}")
    print(f"  error: {_stats(t)}; across the image {_stats(a)}; depth {_stats(z)}")
    big = m > 2.0
    print(f"  where the marker moved over 2 mm ({big.sum()} of {len(m)}): {_stats(t[big])}")
    print(f"  lift per frame (ray cast + GDE spread): {_ms(lift_t)}")

    # Exact 2D positions on the truth's own mesh: ray casting's own error.
    lifter = MarkerLifter(canonical.with_vertices(person), person[vertices], rig)
    names = tuple(m.name for m in rig.markers)
    roles = tuple(m.role for m in rig.markers)
    total, depth = [], []
    for i in range(1, len(frames)):
        pose = Pose(truth["rotation"][i], truth["scale"][i], truth["translation"][i])
        face = truth_wires.deform(truth["wire_params"][i])
        xy = pose.apply(face)[vertices, :2]
        status = tuple(SEEN for _ in names)
        fit = lifter.lift(Markers(names, roles, xy, np.ones(len(xy)), status, pose))
        d = fit.marker_displacement - (face - person)[vertices]
        total.append(np.linalg.norm(d, axis=1) * 10)
        depth.append(camera_split(d, pose.rotation)[1])
    t, z = np.concatenate(total), np.concatenate(depth)
    print(f"  from exact 2D positions on the truth's mesh: {_stats(t)} (depth {_stats(z)})")


def rebuilt(frames: list[np.ndarray], truth: dict[str, Any]) -> None:
    rig = load_rig()
    person = truth["person_vertices"]
    truth_wires = WireDeformer.from_rig(person, rig)
    vertices = truth["marker_vertices"]
    fps = float(truth["fps"])
    rows: dict[str, list[str]] = {}
    for name, tracker in (("landmarks", None), ("markers", MarkerFaceTracker())):
        encoder = FaceEncoder(640, 480, fps, tracker=tracker)
        both = Loopback(encoder, CapturedFrame(0, frames[0], 0), seq=None)
        decoder = both.decoder
        assert encoder.wires is not None
        all_err, marker_err, wire_err, lids, wire_lids, sizes, times = [], [], [], [], [], [], []
        for i, image in enumerate(frames):
            frame = CapturedFrame(i, image, 0)
            t0 = time.perf_counter()
            result = encoder.analyse(image)
            sent = both.send_analysed(frame, result)
            times.append(time.perf_counter() - t0)
            packets = both.receive(sent)
            sizes.append(
                sum(
                    len(d)
                    for d, p in zip(sent, packets, strict=True)
                    if not isinstance(p, RemPatch)
                )
            )
            assert both.shown is not None
            got = decoder.image_vertices(both.shown)
            pose = Pose(truth["rotation"][i], truth["scale"][i], truth["translation"][i])
            want = pose.apply(truth_wires.deform(truth["wire_params"][i]))
            e = np.linalg.norm(got[:, :2] - want[:, :2], axis=1)
            all_err.append(e)
            visible = truth["marker_visible"][i]
            marker_err.append(
                np.linalg.norm(got[vertices, :2] - truth["marker_xy"][i], axis=1)[visible]
            )
            if result is not None:
                wire_pose, params = result
                w = wire_pose.apply(encoder.wires.deform(params))
                wire_err.append(np.linalg.norm(w[:, :2] - want[:, :2], axis=1))
            if i in truth["blink_frames"]:
                lids.append(np.mean([np.linalg.norm(got[a, :2] - got[b, :2]) for a, b in LIDS]))
                if result is not None:
                    gap = [np.linalg.norm(w[a, :2] - w[b, :2]) for a, b in LIDS]
                    wire_lids.append(float(np.mean(gap)))
        both.close()
        a, m = np.concatenate(all_err), np.concatenate(marker_err)
        kbps = np.sum(sizes) * 8 * fps / len(frames) / 1000
        rows[name] = [
            f"{np.median(a):.2f} / {np.percentile(a, 90):.2f}",
            f"{np.median(m):.2f} / {np.percentile(m, 90):.2f}",
            f"{np.median(np.concatenate(wire_err)):.2f}",
            ", ".join(f"{g:.1f}" for g in lids),
            ", ".join(f"{g:.1f}" for g in wire_lids),
            f"{kbps:.2f}",
            _ms(times[1:]),
        ]
    labels = [
        "all 468 vertices, px (median / p90)",
        "the rig's markers, px (median / p90)",
        "wires fitted, before the basis: all vertices, px (median)",
        "lid gap at the 5 blinks, px (truth 4.1; open 14.7)",
        "the same, wires fitted, before the basis",
        "geometry frame packets, kbit/s",
        "sender per frame (track + fit + packet)",
    ]
    print("Rebuilt face against the truth (through packets and the receiver's decoder):")
    print("| | landmarks | markers |")
    print("|---|---|---|")
    for k, label in enumerate(labels):
        print(f"| {label} | {rows['landmarks'][k]} | {rows['markers'][k]} |")


def raycast_speed(truth: dict[str, Any]) -> None:
    canonical = load_canonical()
    person = truth["person_vertices"]
    caster = RayCaster(canonical.triangles, person)
    pose = Pose(truth["rotation"][140], truth["scale"][140], truth["translation"][140])
    xy = truth["marker_xy"][140]
    rays = orthographic_rays(pose, xy)
    for label, cast in (("BVH", caster.cast), ("every triangle", caster.cast_all)):
        t = []
        for _ in range(200):
            t0 = time.perf_counter()
            cast(*rays)
            t.append(time.perf_counter() - t0)
        print(
            f"ray casting {len(xy)} rays on {len(canonical.triangles)} triangles, {label}: {_ms(t)}"
        )
    t = []
    for _ in range(200):
        t0 = time.perf_counter()
        caster.update(person)
        t.append(time.perf_counter() - t0)
    print(f"  refitting the BVH to moved vertices: {_ms(t)}")


def stickers_on(path: str, limit: int) -> None:
    """Real footage with stickers drawn on: the rig's markers (the clip's colours, about 4 %
    of the face's width across) drawn where the landmark tracker puts their vertices, on the
    vertices that face the camera, the video written through MPEG-4 Part 2 and read back,
    then tracked. The landmarks jitter, so the "truth" moves as no sticker would."""
    import tempfile
    from pathlib import Path

    from facewire.sender.landmarks import LandmarkTracker

    rig = load_rig()
    canonical = load_canonical()
    vertices = np.array([m.vertex for m in rig.markers])
    colours = {"pose": (0, 200, 0), "deform": (230, 80, 0), "mouth": (0, 0, 230)}
    landmarks = LandmarkTracker()
    frames, truths = [], []
    radius = 0.0
    with VideoSource(path) as video:
        fps = video.fps
        for frame in video.frames(limit=limit):
            image = frame.image.copy()
            found = landmarks.track(image)
            xy = np.full((len(vertices), 2), np.nan)
            if found is not None:
                facing = -canonical.vertex_normals(found.points)[vertices, 2] > 0.2
                radius = max(1.5, 0.02 * float(np.ptp(found.points[:, 0])))
                for i, m in enumerate(rig.markers):
                    if facing[i]:
                        xy[i] = found.points[m.vertex, :2]
                        c = (int(round(xy[i, 0] * 16)), int(round(xy[i, 1] * 16)))
                        cv2.circle(
                            image, c, int(round(radius * 16)), colours[m.role], -1, cv2.LINE_AA, 4
                        )
            frames.append(image)
            truths.append(xy)
    h, w = frames[0].shape[:2]
    with tempfile.TemporaryDirectory() as tmp:
        clip = Path(tmp) / "stickers.mp4"
        writer = cv2.VideoWriter(str(clip), cv2.VideoWriter.fourcc(*"mp4v"), fps, (w, h))
        for image in frames:
            writer.write(image)
        writer.release()
        tracker = MarkerTracker()
        err, missed, wrong, tracked = [np.zeros(0)], 0, 0, 0
        states: dict[str, int] = {}
        with VideoSource(clip) as video:
            for frame, xy in zip(video.frames(), truths, strict=False):
                found = tracker.track(frame.image)
                states[tracker.state] = states.get(tracker.state, 0) + 1
                if found is None:
                    continue
                tracked += 1
                shown = np.isfinite(xy[:, 0])
                e = np.linalg.norm(found.xy - np.nan_to_num(xy), axis=1)
                err.append(e[shown & found.seen])
                missed += int((shown & ~found.seen).sum())
                wrong += int((e[shown & found.seen] > 5).sum())
    e = np.concatenate(err)
    print(
        f"stickers drawn on {Path(path).name} ({len(frames)} frames, {w}x{h}, stickers "
        f"{2 * radius:.1f} px across): {tracked} frames tracked {states}; "
        + (f"error px {_stats(e)}; " if len(e) else "")
        + f"missed {missed} of {len(e) + missed}; more than 5 px off {wrong}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1, help="OpenCV threads (default 1)")
    parser.add_argument(
        "--stickers",
        metavar="CLIP",
        action="append",
        default=[],
        help="also real footage with stickers drawn on (repeatable); only this is run",
    )
    parser.add_argument("--frames", type=int, default=180, help="frames of each --stickers clip")
    args = parser.parse_args()
    cv2.setNumThreads(args.threads)
    if args.stickers:
        for path in args.stickers:
            stickers_on(path, args.frames)
        return
    truth = dict(np.load(demo_clip_path().with_name("demo_clip_truth.npz")))
    with VideoSource(demo_clip_path()) as video:
        frames = [f.image for f in video.frames()]
    print(f"load average at start: {os.getloadavg()[0]:.1f} (2 cores)")
    markers_2d(frames, truth)
    lift_3d(frames, truth)
    rebuilt(frames, truth)
    raycast_speed(truth)
    print(f"load average at end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
