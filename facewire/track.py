"""``facewire track``: the tracker on its own, landmarks and head pose of every frame as JSON.

The input is a still image (one frame) or a video. Each frame gives the 468 landmarks in the
canonical mesh's vertex order (x, y in input pixels, z relative depth in the same pixel
scale, away from the camera), the model's face-presence score, the head pose and what the
tracker made of the frame (``state``), or an empty list and a null pose when there is no
face. Landmarks of a video are smoothed over time (One Euro filter) unless ``--no-smooth``.
With ``--tracker markers`` a frame gives the rig's coloured markers instead (name, x, y,
confidence, status), and the pose fitted to its pose markers.
"""

from __future__ import annotations

import argparse
import json
import logging
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from facewire.models.mesh import load_canonical
from facewire.models.pose import FRONTAL, Pose, estimate_pose
from facewire.models.rig import load_rig
from facewire.receiver.recorder import Mp4Recorder
from facewire.sender.capture import CaptureError, VideoSource
from facewire.sender.landmarks import ACQUIRED, STATES, TRACKED, Landmarks, LandmarkTracker
from facewire.sender.markers import HIDDEN, MERGED, Markers, MarkerTracker
from facewire.sender.markers import STATES as MARKER_STATES
from facewire.sender.smoothing import LandmarkSmoother

logger = logging.getLogger(__name__)

DECIMALS = 2  # 0.01 px is well below the tracker's own noise
VIDEO_DRAW = (".mp4",)
# Files with these suffixes are images: when OpenCV cannot read one, it is not tried as a
# video (FFmpeg would print its own complaints on stderr).
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".bmp", ".webp", ".tif", ".tiff", ".ppm", ".pgm"}
# Length (cm, model space) of the pose axes drawn from the nose tip.
AXIS_CM = 4.0
NOSE_TIP = 1
STATE_COLOURS = {ACQUIRED: (0, 200, 255), TRACKED: (0, 220, 0)}
ROLE_COLOURS = {"pose": (0, 200, 0), "deform": (230, 80, 0), "mouth": (0, 0, 230)}  # BGR
TRACKERS = ("landmarks", "markers")
# A still image is looked at again on the crop made from its own landmarks, twice: on the
# annotated photos of BENCHMARKS.md this took the inner-face error from 0.070 to 0.058 of
# the inter-ocular distance (the detector's crop is coarser than the tracker's own).
STILL_PASSES = 2


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``track`` on an argparse subparsers object."""
    p = subparsers.add_parser(
        "track",
        help="landmarks and head pose of every frame of an image or video, as JSON",
        description="The tracker on its own: the landmarks (with --tracker markers, the "
        "coloured markers) and the head pose of every frame of an image or a video, as JSON.",
    )
    p.add_argument("--input", metavar="IMAGE_OR_VIDEO", required=True, help="image or video file")
    p.add_argument("--json", metavar="OUT.json", required=True, help="where to write the frames")
    p.add_argument(
        "--draw",
        metavar="OUT.png|OUT.mp4",
        help="the input with the landmarks and pose axes drawn (.mp4 for a video)",
    )
    p.add_argument("--frames", type=int, metavar="N", help="track at most N frames")
    p.add_argument("--no-smooth", action="store_true", help="raw landmarks, no smoothing over time")
    p.add_argument(
        "--tracker",
        choices=TRACKERS,
        default="landmarks",
        help="landmarks (markerless, the default) or markers (coloured stickers at the rig's "
        "markers: see the README)",
    )

    def run(args: argparse.Namespace) -> int:
        return run_track(args)

    p.set_defaults(func=run)


class TrackInput:
    """Frames of an image (one frame, ``fps`` None) or a video, as (h, w, 3) uint8 BGR."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if self.path.is_dir():
            raise CaptureError(f"cannot open {self.path}: it is a folder, not a file")
        if not self.path.is_file():
            raise CaptureError(f"cannot open {self.path}: no such file")
        self.image: np.ndarray | None = None
        self.video: VideoSource | None = None
        if cv2.haveImageReader(str(self.path)):
            self.image = cv2.imread(str(self.path), cv2.IMREAD_COLOR)
        if self.image is None and self.path.suffix.lower() in IMAGE_SUFFIXES:
            raise CaptureError(f"cannot read {self.path}: not an image OpenCV can read")
        if self.image is None:
            try:
                self.video = VideoSource(self.path)
            except CaptureError:
                raise CaptureError(
                    f"cannot read {self.path}: not an image or a video OpenCV can read"
                ) from None
            self.width, self.height = self.video.width, self.video.height
            self.fps: float | None = self.video.fps
        else:
            self.height, self.width = self.image.shape[:2]
            self.fps = None

    @property
    def is_image(self) -> bool:
        return self.image is not None

    def frames(self, limit: int | None = None) -> Iterator[tuple[int, np.ndarray]]:
        if self.image is not None:
            yield 0, self.image
            return
        assert self.video is not None
        for frame in self.video.frames(limit=limit):
            yield frame.index, frame.image

    def close(self) -> None:
        if self.video is not None:
            self.video.close()


class PoseFitter:
    """Head pose of 468 image landmarks: the similarity ``image = scale R model + t`` that
    puts the canonical mesh's pose markers (rig role "pose": nose bridge, nose tip, forehead,
    eye corners, ...) onto the landmarks, by least squares (``facewire.models.pose.estimate_pose``,
    as the sender's encoder does)."""

    def __init__(self) -> None:
        self.canonical = load_canonical().vertices
        self.vertices = np.array(
            sorted({m.vertex for m in load_rig().markers_with_role("pose")}), dtype=np.int64
        )

    def __call__(self, points: np.ndarray) -> Pose:
        return estimate_pose(self.canonical[self.vertices], points[self.vertices])


def yaw_pitch_roll(pose: Pose) -> np.ndarray:
    """(3,) degrees: the head's rotation away from looking straight into the camera.

    Intrinsic rotations of the model about its own up axis (yaw: positive turns the face
    towards image right), then its x axis (pitch: positive tips the face down), then its
    view axis (roll: positive turns the face anticlockwise as seen in the image).
    """
    own = FRONTAL @ pose.rotation  # rotation in model space, before the frontal view
    return Rotation.from_matrix(own).as_euler("YXZ", degrees=True)


def pose_json(pose: Pose) -> dict[str, Any]:
    return {
        "rotation": np.round(pose.rotation, 6).tolist(),
        "translation": np.round(pose.translation, DECIMALS).tolist(),
        "scale": round(pose.scale, 4),
        "yaw_pitch_roll_deg": np.round(yaw_pitch_roll(pose), 2).tolist(),
    }


def frame_json(index: int, state: str, lm: Landmarks | None, pose: Pose | None) -> dict[str, Any]:
    return {
        "index": index,
        "state": state,
        "landmarks": [] if lm is None else np.round(lm.points, DECIMALS).tolist(),
        "confidence": 0.0 if lm is None else round(lm.presence, 4),
        "pose": None if pose is None else pose_json(pose),
    }


def marker_frame_json(index: int, state: str, found: Markers | None) -> dict[str, Any]:
    """A frame's record for the marker tracker: every marker with its confidence."""
    markers = []
    if found is not None:
        for i, name in enumerate(found.names):
            markers.append(
                {
                    "name": name,
                    "role": found.roles[i],
                    "x": round(float(found.xy[i, 0]), DECIMALS),
                    "y": round(float(found.xy[i, 1]), DECIMALS),
                    "confidence": round(float(found.confidence[i]), 3),
                    "status": found.status[i],
                }
            )
    return {
        "index": index,
        "state": state,
        "markers": markers,
        "confidence": 0.0 if found is None else round(float(found.confidence.mean()), 4),
        "pose": None if found is None else pose_json(found.pose),
    }


def draw(
    image: np.ndarray,
    state: str,
    lm: Landmarks | None,
    pose: Pose | None,
    markers: Markers | None = None,
) -> np.ndarray:
    """A copy of ``image`` with the landmarks (or markers: a ring round each seen one, a
    cross where a hidden one is expected), the pose axes and the state written on it."""
    out = image.copy()
    h, w = out.shape[:2]
    unit = max(1, round(max(h, w) / 640))
    dot = unit if max(h, w) >= 400 else 0  # one-pixel dots on small frames
    if lm is not None:
        colour = STATE_COLOURS.get(state, (255, 255, 255))
        for x, y in np.round(lm.points[:, :2]).astype(int):
            cv2.circle(out, (int(x), int(y)), dot, colour, -1, cv2.LINE_AA)
    if markers is not None:
        for (x, y), role, status in zip(markers.xy, markers.roles, markers.status, strict=True):
            c = (int(round(x)), int(round(y)))
            colour = ROLE_COLOURS.get(role, (255, 255, 255))
            if status == HIDDEN:
                cv2.drawMarker(out, c, colour, cv2.MARKER_TILTED_CROSS, 8 * unit, unit)
            else:
                ring = (255, 255, 255) if status == MERGED else (0, 0, 0)
                cv2.circle(out, c, 6 * unit, ring, unit, cv2.LINE_AA)
    if pose is not None:
        canonical = load_canonical().vertices
        base = canonical[NOSE_TIP]
        ends = pose.apply(np.vstack([base, base + AXIS_CM * np.eye(3)]))[:, :2]
        o = tuple(int(v) for v in np.round(ends[0]))
        for end, colour in zip(ends[1:], [(0, 0, 255), (0, 255, 0), (255, 0, 0)], strict=True):
            cv2.line(out, o, tuple(int(v) for v in np.round(end)), colour, 2 * unit, cv2.LINE_AA)
    cv2.putText(
        out, state, (8 * unit, 20 * unit), cv2.FONT_HERSHEY_SIMPLEX, 0.6 * unit, (0, 0, 0), 3 * unit
    )
    cv2.putText(
        out,
        state,
        (8 * unit, 20 * unit),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.6 * unit,
        (255, 255, 255),
        unit,
    )
    return out


class _Drawing:
    """Where drawn frames go: one image file, or an MP4 (padded to an even size, which the
    MP4 writer needs)."""

    def __init__(self, path: Path, src: TrackInput) -> None:
        self.path = path
        self.is_video = path.suffix.lower() in VIDEO_DRAW
        if not self.is_video and not src.is_image:
            raise ValueError(f"--draw {path}: a video's drawing must be an .mp4 file")
        if not self.is_video and not cv2.haveImageWriter(str(path)):
            raise ValueError(f"--draw {path}: not an image type OpenCV writes (try .png)")
        if path.parent and not path.parent.is_dir():
            raise OSError(f"cannot write {path}: folder {path.parent} does not exist")
        self._even = (src.width + src.width % 2, src.height + src.height % 2)
        self._recorder = (
            Mp4Recorder(path, self._even[0], self._even[1], src.fps or 1.0)
            if self.is_video
            else None
        )

    def write(self, image: np.ndarray) -> None:
        if self._recorder is None:
            if not cv2.imwrite(str(self.path), image):
                raise OSError(f"cannot write {self.path}")
            return
        h, w = image.shape[:2]
        if (w, h) != self._even:
            image = cv2.copyMakeBorder(
                image, 0, self._even[1] - h, 0, self._even[0] - w, cv2.BORDER_REPLICATE
            )
        self._recorder.write(image)

    def close(self) -> None:
        if self._recorder is not None:
            self._recorder.close()


def track_still(tracker: LandmarkTracker, image: np.ndarray) -> Landmarks | None:
    """Landmarks of a still image: found, then refined ``STILL_PASSES`` times on its own
    crop (``tracker.state`` stays what the first look gave)."""
    lm = tracker.track(image)
    state = tracker.state
    for _ in range(STILL_PASSES if lm is not None else 0):
        again = tracker.track(image)
        if again is None:
            break
        lm = again
    tracker.state = state
    return lm


def track_markers(
    src: TrackInput, limit: int | None = None, drawing: _Drawing | None = None
) -> list[dict[str, Any]]:
    """The marker tracker over every frame of ``src``; the per-frame records."""
    tracker = MarkerTracker()
    records = []
    for index, image in src.frames(limit):
        found = tracker.track(image)
        records.append(marker_frame_json(index, tracker.state, found))
        if drawing is not None:
            pose = None if found is None else found.pose
            drawing.write(draw(image, tracker.state, None, pose, found))
    return records


def track_frames(
    src: TrackInput, limit: int | None = None, smooth: bool = True, drawing: _Drawing | None = None
) -> list[dict[str, Any]]:
    """Track every frame of ``src``; the per-frame records of the JSON file."""
    smoother = LandmarkSmoother(fps=src.fps) if smooth and src.fps else None
    # A still image gets the whole small-face search at once; a video a few tiles a frame.
    tracker = LandmarkTracker(smoother=smoother, search_budget=None if src.is_image else 4)
    fit_pose = PoseFitter()
    records = []
    for index, image in src.frames(limit):
        t = None if src.fps is None else index / src.fps
        lm = track_still(tracker, image) if src.is_image else tracker.track(image, timestamp_s=t)
        pose = fit_pose(lm.points) if lm is not None else None
        records.append(frame_json(index, tracker.state, lm, pose))
        if drawing is not None:
            drawing.write(draw(image, tracker.state, lm, pose))
    return records


def run_track(args: argparse.Namespace) -> int:
    if args.frames is not None and args.frames < 1:
        raise ValueError(f"--frames must be at least 1, got {args.frames}")
    out = Path(args.json)
    if out.parent and not out.parent.is_dir():
        raise OSError(f"cannot write {out}: folder {out.parent} does not exist")
    src = TrackInput(args.input)
    drawing = _Drawing(Path(args.draw), src) if args.draw else None
    markers = getattr(args, "tracker", "landmarks") == "markers"
    try:
        if markers:
            frames = track_markers(src, args.frames, drawing)
        else:
            frames = track_frames(src, args.frames, not args.no_smooth, drawing)
    finally:
        src.close()
        if drawing is not None:
            drawing.close()
    doc = {
        "input": str(src.path),
        "width": src.width,
        "height": src.height,
        "fps": src.fps,
        "smoothed": bool(src.fps) and not args.no_smooth and not markers,
        "frames": frames,
    }
    if markers:
        doc["tracker"] = "markers"
    out.write_text(json.dumps(doc, separators=(",", ":")) + "\n")
    counts = {
        s: sum(f["state"] == s for f in frames) for s in (MARKER_STATES if markers else STATES)
    }
    with_face = counts[ACQUIRED] + counts[TRACKED]
    detail = ", ".join(f"{n} {s}" for s, n in counts.items() if n)
    what = "markers" if markers else "a face"
    print(f"track: {len(frames)} frames, {with_face} with {what} ({detail}); wrote {out}")
    return 0
