"""Markerless face tracking: MediaPipe's 468-point face landmark model (models/network.py).

Each frame the model sees a square, upright (roll-corrected) crop of the face. The crop comes
from the BlazeFace detector on the first frame and after a loss, and from the previous
frame's landmarks otherwise. Faces too small for the detector's whole-frame pass are looked
for again in tiles (``facewire.sender.detector.TileSearch``), a few tiles per frame, so a video
finds a face down to ``min_face`` px wide within a few frames at a bounded cost per frame.

Points are mapped back to image space: OpenCV pixel coordinates of the input frame (x right,
y down, pixel centres at integers) and z away from the camera in the same pixel scale,
relative to the face (its origin is arbitrary).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from facewire.models.network import Network, rgb_input
from facewire.sender.detector import (
    Detection,
    FaceDetector,
    TileSearch,
    largest_first,
    model_path,
)
from facewire.sender.eyes import EyeRefiner
from facewire.sender.smoothing import LandmarkSmoother

logger = logging.getLogger(__name__)

INPUT_SIZE = 192
# Graph outputs: 468 x (x, y, z) in crop pixels (1, 1, 1, 1404), face-presence logit (1, 1, 1, 1).
OUTPUT_LAYERS = ["conv2d_21", "conv2d_31"]
N_LANDMARKS = 468
# MediaPipe indices that set the crop's roll: the face's right and left outer eye corners.
RIGHT_EYE_OUTER = 33
LEFT_EYE_OUTER = 263
# Crop side relative to the detector box, and to the landmarks' extent (MediaPipe uses 1.5
# for both; the landmark extent excludes the forehead margin the detector box lacks).
DETECTION_SCALE = 1.5
LANDMARK_SCALE = 1.5
# Detections tried with the landmark model per frame before giving up on it (the detector's
# false positives are turned down by the landmark model's presence score).
MAX_CANDIDATES = 3
# For this many frames after a loss only a face where the lost one was is taken back (so a
# second person in view does not take over while the first looks away for a moment);
# "where" is within this fraction of the last crop's side, at half to twice its size.
REACQUIRE_FRAMES = 15
REACQUIRE_DISTANCE = 0.5
# A frame whose pixels all lie within this many grey levels shows nothing (e.g. black).
BLANK_RANGE = 8

#: What :meth:`LandmarkTracker.track` made of the last frame (``LandmarkTracker.state``).
ACQUIRED = "acquired"  # found by the detector in this frame
TRACKED = "tracked"  # followed from the previous frame's landmarks
LOST = "lost"  # followed until the previous frame, gone in this one
NO_FACE = "none"  # no face found
BLANK = "blank"  # the frame is one flat colour: nothing to look for
STATES = (ACQUIRED, TRACKED, LOST, NO_FACE, BLANK)


@dataclass(frozen=True)
class Landmarks:
    """468 face landmarks of one frame.

    points : (468, 3) float64, image space (pixels; z away from the camera, same scale)
    presence : float, 0..1, the model's face-presence probability
    """

    points: np.ndarray
    presence: float


@dataclass(frozen=True)
class Crop:
    """A square, rotated crop: crop pixel q maps to image ``centre + scale * R(angle) @ (q - c)``.

    centre : (2,) image pixels; size : side in image pixels; angle : radians, the image
    direction of the crop's +x axis (the face's right-to-left eye direction).
    """

    centre: np.ndarray
    size: float
    angle: float

    @property
    def pixel_size(self) -> float:
        """Image pixels per pixel of the landmark model's input."""
        return self.size / INPUT_SIZE

    def crop_to_image(self) -> np.ndarray:
        """(2, 3) affine from OpenCV crop pixels to OpenCV image pixels."""
        s = self.pixel_size
        c, si = np.cos(self.angle), np.sin(self.angle)
        a = s * np.array([[c, -si], [si, c]])
        mid = (INPUT_SIZE - 1) / 2
        t = self.centre - a @ np.array([mid, mid])
        return np.hstack([a, t[:, None]])


def eye_angle(right_eye: np.ndarray, left_eye: np.ndarray) -> float:
    """Roll (radians, image frame) of the vector from the face's right eye to its left eye."""
    d = np.asarray(left_eye, dtype=np.float64) - np.asarray(right_eye, dtype=np.float64)
    return float(np.arctan2(d[1], d[0]))


def crop_from_detection(det: Detection) -> Crop:
    """Upright square crop around a detection, enlarged by ``DETECTION_SCALE``."""
    angle = eye_angle(det.keypoints[0], det.keypoints[1])
    return Crop(det.centre, DETECTION_SCALE * det.size, angle)


def crop_from_points(points: np.ndarray) -> Crop:
    """Upright square crop around landmarks ((468, 2+) image pixels).

    The extent is measured in the face's own (roll-corrected) frame, so a rolled face gets
    the same crop size as an upright one.
    """
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    angle = eye_angle(xy[RIGHT_EYE_OUTER], xy[LEFT_EYE_OUTER])
    c, s = np.cos(angle), np.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    local = xy @ rot  # rows are rot.T @ p: image -> face-aligned frame
    lo, hi = local.min(axis=0), local.max(axis=0)
    centre = rot @ ((lo + hi) / 2)
    return Crop(centre, LANDMARK_SCALE * float((hi - lo).max()), angle)


def sigmoid(x: float) -> float:
    return float(1.0 / (1.0 + np.exp(-np.clip(x, -100.0, 100.0))))


def is_blank(frame_bgr: np.ndarray) -> bool:
    """True if every pixel (sampled every 4th row and column) lies within ``BLANK_RANGE``."""
    # A sparse look first: any ordinary frame varies there, and that is decided in ~10 us.
    sparse = frame_bgr[::16, ::16]
    if int(sparse.max()) - int(sparse.min()) > BLANK_RANGE:
        return False
    sample = frame_bgr[::4, ::4]
    return int(sample.max()) - int(sample.min()) <= BLANK_RANGE


class LandmarkTracker:
    """Follows one face from frame to frame and returns its 468 landmarks.

    Input normalisation is RGB scaled to [0, 1]. Checked on the astronaut fixture over 12
    jittered crops: presence logit >= 23.8 and 0.95 px RMS landmark spread with [0, 1],
    against >= 22.9 and 1.13 px with [-1, 1] (both "work"; [0, 1] is the model's own).
    Thread count is whatever the caller set with ``cv2.setNumThreads``.

    With several faces in view it takes the largest one and keeps following that one
    until it is lost; for ``REACQUIRE_FRAMES`` frames after a loss it takes back only a
    face where the lost one was. ``min_face`` (px, landmark width) is the smallest face looked for:
    faces below the whole-frame pass's reach are searched for in tiles, ``search_budget``
    tiles per frame while no face is tracked (None: all of them in one frame, for a still
    image); ``min_face=None`` turns the tile search off. ``smoother`` (optional) filters
    the returned points over time; the next crop always comes from the unfiltered points.
    ``refine_eyes`` runs the eye model over both eye regions (``facewire.sender.eyes``; without it
    the face model's eyes barely blink). :attr:`state` says what the last frame gave (one of
    ``STATES``).
    """

    def __init__(
        self,
        path: str | Path | None = None,
        detector: FaceDetector | None = None,
        min_presence: float = 0.5,
        min_face: float | None = 48.0,
        search_budget: int | None = 4,
        smoother: LandmarkSmoother | None = None,
        refine_eyes: bool = True,
    ) -> None:
        self.path = Path(path) if path is not None else model_path("face_landmark.tflite")
        self.net = Network(self.path)
        self.detector = detector if detector is not None else FaceDetector()
        self.min_presence = min_presence
        self.search = TileSearch(self.detector, min_face) if min_face is not None else None
        self.search_budget = search_budget
        self.smoother = smoother
        self.eyes = EyeRefiner() if refine_eyes else None
        self.state = NO_FACE
        self._crop: Crop | None = None
        self._last: Crop | None = None  # where the face was last seen
        self._since_lost = 0  # frames since it was lost

    def reset(self) -> None:
        """Forget the face: the next frame runs the detector and may take any face."""
        self._drop()
        self._last = None

    def _drop(self) -> None:
        """The face is lost: look for one again, first where it was."""
        if self._crop is not None:
            self._last, self._since_lost = self._crop, 0
        self._crop = None
        if self.search is not None:
            self.search.restart()

    def _near_last(self, det: Detection) -> bool:
        last = self._last
        if last is None:
            return True
        face = last.size / LANDMARK_SCALE
        close = np.linalg.norm(det.centre - last.centre) <= REACQUIRE_DISTANCE * last.size
        return bool(close and 0.5 * face <= det.size <= 2.0 * face)

    @property
    def crop(self) -> Crop | None:
        """The crop the next frame will use (None: the detector chooses it)."""
        return self._crop

    def run_crop(self, frame_bgr: np.ndarray, crop: Crop) -> Landmarks:
        """Landmarks of the face in ``crop`` of ``frame_bgr``, whatever its presence."""
        m = crop.crop_to_image()
        patch = cv2.warpAffine(
            frame_bgr,
            m,
            (INPUT_SIZE, INPUT_SIZE),
            flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_CONSTANT,
        )
        outputs = self.net.run(rgb_input(patch, 1 / 255.0))
        raw, logit = (outputs[name] for name in OUTPUT_LAYERS)
        pts = raw.reshape(N_LANDMARKS, 3).astype(np.float64)
        # The model's coordinates are continuous (pixel i spans [i, i+1)); OpenCV's pixel
        # centres are at integers.
        q = pts[:, :2] - 0.5
        out = np.empty_like(pts)
        out[:, :2] = q @ m[:, :2].T + m[:, 2]
        # MediaPipe z is more negative closer to the camera, which is our "away from the
        # camera" sign already; only the crop's scale applies (roll is about the z axis).
        out[:, 2] = pts[:, 2] * (crop.size / INPUT_SIZE)
        return Landmarks(out, sigmoid(float(logit.ravel()[0])))

    def _verify(self, frame_bgr: np.ndarray, dets: list[Detection]) -> Landmarks | None:
        """Landmarks of the face to follow among the detector's candidates, or None.

        The ``MAX_CANDIDATES`` best-scoring candidates go through the landmark model, whose
        presence score turns down the detector's false positives; of those it accepts, the
        largest face is taken (``largest_first``).
        """
        found: list[tuple[Detection, Landmarks]] = []
        for det in sorted(dets, key=lambda d: -d.score)[:MAX_CANDIDATES]:
            lm = self.run_crop(frame_bgr, crop_from_detection(det))
            if lm.presence >= self.min_presence:
                found.append((det, lm))
            else:
                logger.debug("candidate at %s turned down: presence %.3f", det.centre, lm.presence)
        if found and self._last is not None and self._since_lost <= REACQUIRE_FRAMES:
            found = [(d, lm) for d, lm in found if self._near_last(d)]
            if not found:
                logger.debug("waiting for the lost face: %d frames", self._since_lost)
        if not found:
            return None
        h, w = frame_bgr.shape[:2]
        chosen = largest_first([d for d, _ in found], w, h)[0]
        return next(lm for d, lm in found if d is chosen)

    def _acquire(self, frame_bgr: np.ndarray) -> Landmarks | None:
        """A face in a frame with none tracked: the detector on the whole frame, and when
        that gives nothing, the next tiles of the small-face search."""
        lm = self._verify(frame_bgr, self.detector.detect(frame_bgr))
        if lm is None and self.search is not None:
            lm = self._verify(frame_bgr, self.search.scan(frame_bgr, self.search_budget))
        return lm

    def track(self, frame_bgr: np.ndarray, timestamp_s: float | None = None) -> Landmarks | None:
        """Landmarks of the face in ``frame_bgr`` ((h, w, 3) uint8 BGR), or None if none.

        After a None the next call looks for a face again. ``timestamp_s`` (seconds, any
        origin) times the frame for the smoother; None means one frame after the last.
        """
        if frame_bgr.ndim != 3 or frame_bgr.shape[2] != 3 or frame_bgr.dtype != np.uint8:
            raise ValueError(
                f"expected (h, w, 3) uint8 BGR frame, got {frame_bgr.shape} {frame_bgr.dtype}"
            )
        self._since_lost += 1
        if is_blank(frame_bgr):
            self._drop()
            self.state = BLANK
            return None
        lm: Landmarks | None = None
        was_tracking = self._crop is not None
        if self._crop is not None:
            lm = self.run_crop(frame_bgr, self._crop)
            self.state = TRACKED
            if lm.presence < self.min_presence:
                logger.debug("face lost: presence %.3f < %.3f", lm.presence, self.min_presence)
                self._drop()
                lm = None
        if lm is None:
            # Also right after a loss: a face that jumped out of the crop is found at once.
            lm = self._acquire(frame_bgr)
            self.state = ACQUIRED if lm is not None else LOST if was_tracking else NO_FACE
        if lm is None:
            return None
        self._crop = crop_from_points(lm.points)
        if self.eyes is not None:
            lm = Landmarks(self.eyes.refine(frame_bgr, lm.points), lm.presence)
        if self.smoother is not None:
            if self.state == ACQUIRED:
                self.smoother.reset()
            lm = Landmarks(self.smoother(lm.points, timestamp_s), lm.presence)
        return lm
