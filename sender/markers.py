"""Coloured sticker markers on the face, tracked frame to frame (the seeds' capture set-up).

Behind the same interface as the landmark tracker (``track(frame)``, ``state``, ``STATES``),
:class:`MarkerTracker` returns the rig's markers (``models/data/rig.json``: names, roles,
vertices) as named 2D points with a confidence each.

- Calibration, at the first frame with a face: the landmark tracker says roughly where each
  marker's vertex is, and the colours found there become the colour classes
  (``facewire.sender.marker_colours``). Each marker's place on the face, the *layout*, is the
  point of the landmarks' mesh under it (a ray cast, ``facewire.models.raycast``). Over the
  next few frames the classes are read again from every marker found, so they settle on
  the clip's own colours.
- Every frame: pyramidal Lucas-Kanade carries each marker seen in the last frame to where it
  should be now; from those, the head pose (``facewire.models.pose2d``, the layout's pose
  markers) places the markers that were hidden, where the layout says they are plus the offset they
  had when last seen. Blobs of each colour class are found around the face, a blob large
  enough for two with two predictions in it is split between them (a blink brings the lid
  markers together), and markers take blobs by an optimal assignment within a gate that
  is tight for a marker followed by LK and wider the longer a marker has been hidden. A
  marker's position is its blob's centroid; a marker without a blob is hidden, placed where
  it was predicted, with confidence 0.
- Pose markers that sit badly with the others after the assignment (a wrong blob) are
  dropped and the pose fitted again; with fewer than 3 pose markers the frame is lost, and
  after a while without markers the landmark tracker looks for the face again so the layout
  can be placed anew.

Coordinates are OpenCV pixels of the input frame (pixel centres at integers).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from facewire.models.mesh import FaceMesh, load_canonical
from facewire.models.pose import Pose, estimate_pose
from facewire.models.pose2d import estimate_pose_2d
from facewire.models.raycast import RayCaster, orthographic_rays
from facewire.models.rig import Rig, load_rig
from facewire.sender.landmarks import Landmarks, LandmarkTracker, is_blank
from facewire.sender.marker_colours import (
    MIN_AREA_FRACTION,
    MIN_MARKER_SATURATION,
    Blobs,
    ColourClass,
    MarkerSample,
    class_mask,
    colour_classes,
    find_blobs,
    sample_marker,
    split_blob,
)

logger = logging.getLogger(__name__)

#: What :meth:`MarkerTracker.track` made of the last frame (``MarkerTracker.state``).
ACQUIRED = "acquired"  # calibrated, or markers found again after a loss
TRACKED = "tracked"  # followed from the last frame
LOST = "lost"  # too few pose markers in this frame
NO_FACE = "none"  # not calibrated yet and no face found
BLANK = "blank"  # the frame is one flat colour
NO_MARKERS = "no_markers"  # a face, but not enough markers on it to calibrate
STATES = (ACQUIRED, TRACKED, LOST, NO_FACE, BLANK, NO_MARKERS)

#: What became of each marker in the last frame (``Markers.status``).
SEEN = "seen"  # its own blob
MERGED = "merged"  # shares a blob with another marker (split between them)
HIDDEN = "hidden"  # no blob: placed where it was predicted
MARKER_STATUSES = (SEEN, MERGED, HIDDEN)

# Calibration: at least this many pose markers (the pose needs 4 not in a plane to start).
MIN_POSE_MARKERS = 4
# A colour class that covers more than this fraction of the face away from the markers is
# the face's own colour (measured: the bundled clip's classes 0.02 % at most, the skin hue
# picked up on a face without markers 22 %).
MAX_CLUTTER = 0.02
# Calibration window around a marker's expected place, cm of face (min 5 px).
CALIBRATION_RADIUS_CM = 0.45
# Colour classes are read again from the markers found over this many frames.
CALIBRATION_FRAMES = 8
# Gates (cm of face; px = cm x the pose's scale): a marker followed by LK, a marker placed
# by the layout (growing per hidden frame up to the maximum).
LK_GATE_CM = 0.4
LAYOUT_GATE_CM = 0.7
LAYOUT_GATE_GROWTH_CM = 0.05
LAYOUT_GATE_MAX_CM = 1.6
MIN_GATE_PX = 3.0
# A pose marker further than this from the fitted pose (cm) has taken a wrong blob.
POSE_OUTLIER_CM = 0.6
# A blob this much larger than one marker, with two predictions in it, holds two markers.
MERGE_AREA = 1.4
# A marker's centroid is taken within this many of its radii of the blob's centre.
REACH = 1.6
# Confidence of a marker sharing a blob.
MERGED_CONFIDENCE = 0.9
# Region searched for blobs: the predictions' box grown by this much (cm).
ROI_MARGIN_CM = 2.0
# Frames lost before the landmark tracker is asked where the face is, and then every so often.
LANDMARK_RETRY_FRAMES = 10
LK_WINDOW = (15, 15)
LK_LEVELS = 2
LK_MARGIN_CM = 1.5
LK_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.03)
# LK's own error (mean absolute intensity difference) above which its answer is not used.
LK_MAX_ERROR = 30.0


@dataclass(frozen=True)
class Markers:
    """The rig's markers in one frame.

    names, roles : (k,) the rig's, in its order
    xy : (k, 2) float64, image pixels (for a hidden marker: where it was predicted)
    confidence : (k,) float64, 0..1 (0: hidden)
    status : (k,) one of ``MARKER_STATUSES`` each
    pose : the head pose fitted to the pose markers (model space: the tracker's layout)
    """

    names: tuple[str, ...]
    roles: tuple[str, ...]
    xy: np.ndarray
    confidence: np.ndarray
    status: tuple[str, ...]
    pose: Pose

    @property
    def seen(self) -> np.ndarray:
        """(k,) bool: the marker has a blob in this frame."""
        return np.array([s != HIDDEN for s in self.status])

    def index(self, name: str) -> int:
        return self.names.index(name)


@dataclass
class _Calibration:
    classes: list[ColourClass]
    marker_class: np.ndarray  # (k,) class index of each marker
    area: float  # a marker's blob area, px
    samples: list[list[MarkerSample]]  # per marker, the samples read so far


class MarkerTracker:
    """Follows the rig's coloured markers from frame to frame.

    rig : the markers' names, roles and vertices (default: the bundled rig)
    landmarks : the landmark tracker used to calibrate and to find the face after a long
        loss (default: a new one without smoothing)
    """

    def __init__(self, rig: Rig | None = None, landmarks: LandmarkTracker | None = None) -> None:
        self.rig = rig or load_rig()
        self.landmarks = landmarks if landmarks is not None else LandmarkTracker()
        self.canonical = load_canonical()
        self.names = tuple(m.name for m in self.rig.markers)
        self.roles = tuple(m.role for m in self.rig.markers)
        self.vertices = np.array([m.vertex for m in self.rig.markers], dtype=np.int64)
        self.pose_markers = np.flatnonzero(np.array(self.roles) == "pose")
        self.state = NO_FACE
        self.calibration: _Calibration | None = None
        #: (k, 3) where each marker sits on the face, model space (cm): set by calibration.
        self.layout = np.zeros((len(self.names), 3))
        #: The mesh the layout was read from (model space) and the calibration frame's pose.
        self.mesh: FaceMesh | None = None
        self.calibration_pose: Pose | None = None
        #: Landmarks of the last frame the landmark tracker looked at (calibration, re-finding).
        self.last_landmarks: Landmarks | None = None
        self.reset()

    def reset(self) -> None:
        """Forget the colours and the face: the next frame calibrates again."""
        self.calibration = None
        self.state = NO_FACE
        self._pose: Pose | None = None
        self._xy = np.zeros((len(self.names), 2))
        self._seen = np.zeros(len(self.names), dtype=bool)
        self._hidden_for = np.zeros(len(self.names), dtype=np.int64)
        self._offset = np.zeros((len(self.names), 2))  # image offset from the layout when seen
        self._grey: np.ndarray | None = None
        self._lost_for = 0
        self._frames = 0
        self.landmarks.reset()

    @property
    def calibrated(self) -> bool:
        return self.calibration is not None

    @property
    def scale(self) -> float:
        """Pixels per cm of face at the last pose."""
        return self._pose.scale if self._pose is not None else 1.0

    # -- calibration ---------------------------------------------------------------------

    def calibrate(self, frame_bgr: np.ndarray, points: np.ndarray) -> bool:
        """Read the marker colours and the layout from a frame and its 468 landmarks
        ((468, 3) image space, as ``LandmarkTracker`` gives them). False (state
        ``NO_MARKERS``) when fewer than ``MIN_POSE_MARKERS`` pose markers are found."""
        pose_v = self.vertices[self.pose_markers]
        pose0 = estimate_pose(self.canonical.vertices[pose_v], points[pose_v])
        radius = max(5.0, CALIBRATION_RADIUS_CM * pose0.scale)
        expected = points[self.vertices, :2]
        found: list[MarkerSample | None] = [sample_marker(frame_bgr, e, radius) for e in expected]
        usable = [s is not None and s.saturation >= MIN_MARKER_SATURATION for s in found]
        # Two markers must not claim one blob: the nearer keeps it.
        for i in range(len(found)):
            for j in range(i + 1, len(found)):
                si, sj = found[i], found[j]
                if usable[i] and usable[j] and si is not None and sj is not None:
                    if np.linalg.norm(si.centroid - sj.centroid) < 1.0:
                        di = np.linalg.norm(si.centroid - expected[i])
                        dj = np.linalg.norm(sj.centroid - expected[j])
                        usable[j if dj > di else i] = False
        # A colour that much of the face itself has (skin, lips, hair) is no marker colour.
        while any(usable):
            kept = [s for s, u in zip(found, usable, strict=True) if u and s is not None]
            classes, group = colour_classes(kept)
            clutter = face_clutter(frame_bgr, points[:, :2], classes, kept)
            bad = [c for c, f in enumerate(clutter) if f > MAX_CLUTTER]
            if not bad:
                break
            for c in bad:
                logger.info(
                    "colour %s is all over the face (%.1f %%): not a marker colour",
                    classes[c].label(),
                    100 * clutter[c],
                )
            owners = np.flatnonzero(usable)
            for i, g in zip(owners.tolist(), group.tolist(), strict=True):
                if g in bad:
                    usable[i] = False
        n_pose = sum(usable[i] for i in self.pose_markers)
        if n_pose < MIN_POSE_MARKERS:
            logger.info(
                "no markers to calibrate on: %d of %d pose markers found (%d markers in all)",
                n_pose,
                len(self.pose_markers),
                sum(usable),
            )
            self.state = NO_MARKERS
            return False
        samples = [s for s, u in zip(found, usable, strict=True) if u and s is not None]
        classes, group = colour_classes(samples)
        marker_class = np.full(len(self.names), -1, dtype=np.int64)
        marker_class[np.flatnonzero(usable)] = group
        # A marker not found gets the class of the nearest-hued class of its role's markers,
        # or the most common class: it may still turn up later.
        for i in np.flatnonzero(marker_class < 0).tolist():
            same_role = [
                marker_class[j]
                for j in range(len(self.names))
                if self.roles[j] == self.roles[i] and marker_class[j] >= 0
            ]
            pool = same_role or list(marker_class[marker_class >= 0])
            marker_class[i] = int(np.bincount(pool).argmax())
        area = float(np.median([s.area for s in samples]))
        self.calibration = _Calibration(
            classes,
            marker_class,
            area,
            [[s] if s is not None and u else [] for s, u in zip(found, usable, strict=True)],
        )
        # The layout: the landmarks' mesh in model space, under each marker.
        model = pose0.inverse(points)
        self.mesh = self.canonical.with_vertices(model)
        xy = expected.copy()
        seen = np.array(usable)
        for i in np.flatnonzero(seen).tolist():
            sample = found[i]
            assert sample is not None
            xy[i] = sample.centroid
        xy = self._measure(frame_bgr, xy, seen, radius)
        self.layout = lift_points(self.mesh, pose0, xy, self.vertices)
        self.calibration_pose = pose0
        self._pose = estimate_pose_2d(
            self.layout[self.pose_markers],
            xy[self.pose_markers],
            seen[self.pose_markers] * 1.0,
            pose0,
        )
        self._xy, self._seen = xy, seen
        self._hidden_for = np.where(seen, 0, 1)
        self._offset = np.zeros((len(self.names), 2))
        self._lost_for = 0
        self._frames = 0
        logger.info(
            "markers calibrated: %d of %d found, %d colour classes (%s), marker area %.0f px",
            int(seen.sum()),
            len(self.names),
            len(classes),
            "; ".join(c.label() for c in classes),
            area,
        )
        return True

    def _measure(
        self, frame_bgr: np.ndarray, xy: np.ndarray, seen: np.ndarray, radius: float
    ) -> np.ndarray:
        """Centroids of the ``seen`` markers near ``xy`` as tracking measures them (its blobs
        and weights), so that later frames compare like with like."""
        cal = self.calibration
        assert cal is not None
        h, w = frame_bgr.shape[:2]
        lo = np.floor(np.maximum(xy[seen].min(axis=0) - 2 * radius, 0)).astype(int)
        hi = np.ceil(np.minimum(xy[seen].max(axis=0) + 2 * radius + 1, [w, h])).astype(int)
        hsv = cv2.cvtColor(frame_bgr[lo[1] : hi[1], lo[0] : hi[0]], cv2.COLOR_BGR2HSV)
        reach = REACH * np.sqrt(cal.area / np.pi)
        found = find_blobs(
            hsv, cal.classes, (int(lo[0]), int(lo[1])), MIN_AREA_FRACTION * cal.area, reach
        )
        out = xy.copy()
        status = [HIDDEN] * len(xy)
        confidence = np.zeros(len(xy))
        gates = np.full(len(xy), radius)
        for c, blobs in enumerate(found):
            members = np.flatnonzero((cal.marker_class == c) & seen)
            self._assign(blobs, members, xy, gates, out, status, confidence)
        return np.where(np.array([s != HIDDEN for s in status])[:, None], out, xy)

    def recalibrate_layout(self, points: np.ndarray) -> None:
        """The layout read again from (468, 3) landmarks of the calibration frame (e.g. moved
        onto the markers): each marker sits on the mesh they make, under its marker."""
        assert self.calibration_pose is not None
        pose_v = self.vertices[self.pose_markers]
        pose0 = estimate_pose(self.canonical.vertices[pose_v], points[pose_v])
        self.mesh = self.canonical.with_vertices(pose0.inverse(points))
        self.layout = lift_points(self.mesh, pose0, self._xy, self.vertices)
        self.calibration_pose = pose0
        self._pose = estimate_pose_2d(
            self.layout[self.pose_markers],
            self._xy[self.pose_markers],
            self._seen[self.pose_markers] * 1.0,
            pose0,
        )

    def _recalibrate(self, hsv_of: dict[int, MarkerSample]) -> None:
        """Classes read again from every sample so far (the first frames)."""
        cal = self.calibration
        assert cal is not None
        for i, s in hsv_of.items():
            cal.samples[i].append(s)
        pooled = [s for per in cal.samples for s in per]
        classes, group = colour_classes(pooled)
        owners = [i for i, per in enumerate(cal.samples) for _ in per]
        marker_class = cal.marker_class.copy()
        votes: dict[int, list[int]] = {}
        for owner, g in zip(owners, group, strict=True):
            votes.setdefault(owner, []).append(int(g))
        if len(classes) != len(cal.classes):
            return  # the colours did not settle into the same classes: keep the first frame's
        for owner, gs in votes.items():
            marker_class[owner] = int(np.bincount(gs).argmax())
        cal.classes = classes
        cal.marker_class = marker_class
        cal.area = float(np.median([s.area for s in pooled]))

    # -- tracking ------------------------------------------------------------------------

    def track(self, frame_bgr: np.ndarray, timestamp_s: float | None = None) -> Markers | None:
        """The markers in ``frame_bgr`` ((h, w, 3) uint8 BGR), or None (see :attr:`state`).

        ``timestamp_s`` is accepted for the landmark tracker's interface and not used.
        """
        if frame_bgr.ndim != 3 or frame_bgr.shape[2] != 3 or frame_bgr.dtype != np.uint8:
            raise ValueError(
                f"expected (h, w, 3) uint8 BGR frame, got {frame_bgr.shape} {frame_bgr.dtype}"
            )
        if is_blank(frame_bgr):
            self.state = BLANK
            self._grey = None
            self._lost_for += 1
            return None
        if self.calibration is None:
            lm = self.landmarks.track(frame_bgr)
            if lm is None:
                self.state = NO_FACE
                return None
            self.last_landmarks = lm
            if not self.calibrate(frame_bgr, lm.points):
                return None
            self._grey = cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY)
            self.state = ACQUIRED
            return self._result()
        return self._follow(frame_bgr)

    def _follow(self, frame_bgr: np.ndarray) -> Markers | None:
        cal = self.calibration
        assert cal is not None and self._pose is not None
        grey = cv2.cvtColor(frame_bgr, cv2.COLOR_BGR2GRAY)
        was_lost = self.state in (LOST, BLANK)
        if (
            was_lost
            and self._lost_for >= LANDMARK_RETRY_FRAMES
            and (self._lost_for % LANDMARK_RETRY_FRAMES == 0)
        ):
            self._place_from_landmarks(frame_bgr)
        predicted, gates, by_lk, layout_xy, layout_gates = self._predict(grey)
        h, w = grey.shape
        margin = ROI_MARGIN_CM * self.scale
        lo = np.floor(np.maximum(predicted.min(axis=0) - margin, 0)).astype(int)
        hi = np.ceil(np.minimum(predicted.max(axis=0) + margin + 1, [w, h])).astype(int)
        if was_lost or (hi <= lo).any():
            lo, hi = np.array([0, 0]), np.array([w, h])
        region = frame_bgr[lo[1] : hi[1], lo[0] : hi[0]]
        hsv = cv2.cvtColor(region, cv2.COLOR_BGR2HSV)
        xy = predicted.copy()
        status = [HIDDEN] * len(self.names)
        confidence = np.zeros(len(self.names))
        samples: dict[int, MarkerSample] = {}
        reach = REACH * np.sqrt(cal.area / np.pi)
        found = find_blobs(
            hsv, cal.classes, (int(lo[0]), int(lo[1])), MIN_AREA_FRACTION * cal.area, reach
        )
        for c, blobs in enumerate(found):
            members = np.flatnonzero(cal.marker_class == c)
            taken = self._assign(blobs, members, predicted, gates, xy, status, confidence)
            # A marker LK took astray gets a second look where the layout puts it.
            again = np.array([i for i in members.tolist() if status[i] == HIDDEN and by_lk[i]])
            if len(again):
                self._assign(
                    blobs, again, layout_xy, layout_gates, xy, status, confidence, skip=taken
                )
            if self._frames < CALIBRATION_FRAMES:
                for i in members.tolist():
                    if status[i] == SEEN:
                        samples[i] = self._sample(hsv, lo, xy[i])
        seen = np.array([s != HIDDEN for s in status])
        pose = self._fit_pose(xy, confidence, seen, status)
        seen = np.array([s != HIDDEN for s in status])
        self._grey = grey
        if pose is None:
            # Too few pose markers: hold what was known, look again next frame.
            self._hidden_for += 1
            self._seen[:] = False
            self._lost_for += 1
            self.state = LOST
            return None
        self._pose = pose
        layout_xy = pose.apply(self.layout)[:, :2]
        self._offset[seen] = xy[seen] - layout_xy[seen]
        # A hidden marker follows the head at its last offset.
        xy[~seen] = layout_xy[~seen] + self._offset[~seen]
        self._xy, self._seen = xy, seen
        self._hidden_for = np.where(seen, 0, self._hidden_for + 1)
        self.state = ACQUIRED if was_lost else TRACKED
        self._lost_for = 0
        if self._frames < CALIBRATION_FRAMES and samples:
            self._recalibrate(samples)
        self._frames += 1
        return Markers(self.names, self.roles, xy, confidence, tuple(status), pose)

    def _result(self) -> Markers:
        assert self._pose is not None
        status = tuple(SEEN if s else HIDDEN for s in self._seen)
        return Markers(
            self.names, self.roles, self._xy.copy(), self._seen * 1.0, status, self._pose
        )

    def _sample(self, hsv: np.ndarray, lo: np.ndarray, centre: np.ndarray) -> MarkerSample:
        """Hue, saturation and value at a marker's centre (3x3 median), for recalibration."""
        x, y = int(round(centre[0])) - lo[0], int(round(centre[1])) - lo[1]
        patch = hsv[max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2].reshape(-1, 3).astype(float)
        cal = self.calibration
        assert cal is not None
        hue = float(np.median(patch[:, 0]))
        return MarkerSample(
            centre.copy(),
            cal.area,
            hue,
            float(np.median(patch[:, 1])),
            float(np.median(patch[:, 2])),
        )

    def _predict(
        self, grey: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Where each marker should be in this frame and its gate (px), which markers LK
        placed, and where the layout places every marker with its gate (px)."""
        assert self._pose is not None
        k = len(self.names)
        predicted = self._xy.copy()
        by_lk = np.zeros(k, dtype=bool)
        if self._grey is not None and self._grey.shape == grey.shape and self._seen.any():
            idx = np.flatnonzero(self._seen)
            # LK on the region round the markers only (building the pyramids of the whole
            # frame was most of its cost): room for a fast head's motion and LK's window.
            h, w = grey.shape
            margin = LK_MARGIN_CM * self.scale + LK_WINDOW[0] * 2**LK_LEVELS / 2
            lo = np.floor(np.maximum(self._xy[idx].min(axis=0) - margin, 0)).astype(int)
            hi = np.ceil(np.minimum(self._xy[idx].max(axis=0) + margin + 1, [w, h])).astype(int)
            p0 = (self._xy[idx] - lo).astype(np.float32).reshape(-1, 1, 2)
            p1, ok, err = cv2.calcOpticalFlowPyrLK(
                self._grey[lo[1] : hi[1], lo[0] : hi[0]],
                grey[lo[1] : hi[1], lo[0] : hi[0]],
                p0,
                p0.copy(),
                winSize=LK_WINDOW,
                maxLevel=LK_LEVELS,
                criteria=LK_CRITERIA,
            )
            good = (ok.ravel() == 1) & (err.ravel() < LK_MAX_ERROR)
            predicted[idx[good]] = p1.reshape(-1, 2)[good] + lo
            by_lk[idx[good]] = True
        # The head's motion from the markers LK followed places the others.
        pose = self._pose
        lk_pose = by_lk[self.pose_markers]
        if lk_pose.sum() >= 3:
            try:
                pose = estimate_pose_2d(
                    self.layout[self.pose_markers],
                    predicted[self.pose_markers],
                    lk_pose * 1.0,
                    self._pose,
                )
            except ValueError:
                pose = self._pose
        layout_xy = pose.apply(self.layout)[:, :2] + self._offset
        predicted[~by_lk] = layout_xy[~by_lk]
        s = pose.scale
        grown = LAYOUT_GATE_CM + LAYOUT_GATE_GROWTH_CM * self._hidden_for
        layout_gates = np.maximum(MIN_GATE_PX, np.minimum(grown, LAYOUT_GATE_MAX_CM) * s)
        gates = np.where(by_lk, max(MIN_GATE_PX, LK_GATE_CM * s), layout_gates)
        return predicted, gates, by_lk, layout_xy, layout_gates

    def _assign(
        self,
        blobs: Blobs,
        members: np.ndarray,
        predicted: np.ndarray,
        gates: np.ndarray,
        xy: np.ndarray,
        status: list[str],
        confidence: np.ndarray,
        skip: set[int] | None = None,
    ) -> set[int]:
        """Markers ``members`` of one colour class take blobs (writes xy, status, confidence);
        the blobs in ``skip`` are not offered. Returns the blobs taken."""
        cal = self.calibration
        assert cal is not None
        skip = skip or set()
        if not len(blobs) or not len(members):
            return set()
        cents = list(blobs.centroids)
        areas = list(blobs.areas)
        merged = [False] * len(cents)
        # A blob with room for two or more markers and as many predictions in it is split.
        radius = np.sqrt(cal.area / np.pi)
        for b in range(len(blobs)):
            if blobs.areas[b] < MERGE_AREA * cal.area or b in skip:
                continue
            x0, y0, x1, y1 = blobs.boxes[b]
            p = predicted[members]
            inside = (
                (p[:, 0] >= x0 - radius)
                & (p[:, 0] <= x1 + radius)
                & (p[:, 1] >= y0 - radius)
                & (p[:, 1] <= y1 + radius)
            )
            near = members[inside]
            if len(near) < 2:
                continue
            near = near[: max(2, min(len(near), int(round(blobs.areas[b] / cal.area))))]
            pixels, weights = blobs.pixels(b)
            parts = split_blob(pixels, weights, predicted[near])
            cents[b] = parts[0]
            areas[b] = blobs.areas[b] / len(parts)
            merged[b] = True
            for part in parts[1:]:
                cents.append(part)
                areas.append(blobs.areas[b] / len(parts))
                merged.append(True)
        c = np.array(cents)
        dist = np.linalg.norm(predicted[members][:, None] - c[None], axis=2)
        cost = (dist / gates[members][:, None]) ** 2
        cost[:, [b for b in skip if b < len(cost[0])]] = np.inf
        big = 1e6
        rows, cols = linear_sum_assignment(np.where(cost <= 1.0, cost, big))
        taken: dict[int, int] = {}  # blob -> the marker that took it
        for r, b in zip(rows.tolist(), cols.tolist(), strict=True):
            if cost[r, b] > 1.0:
                continue
            i = int(members[r])
            taken[b] = i
            xy[i] = c[b]
            ratio = areas[b] / cal.area
            quality = float(np.clip(min(ratio, 1.0 / max(ratio, 1e-6)), 0.0, 1.0)) ** 0.5
            agree = 1.0 - 0.2 * float(cost[r, b])  # a blob at the edge of its gate
            confidence[i] = quality * agree * (MERGED_CONFIDENCE if merged[b] else 1.0)
            status[i] = MERGED if merged[b] else SEEN
        # A marker left without a blob shares one big enough for two that a single marker
        # took, if it is within its gate (the lids in a blink, one of them hidden before).
        for i in members.tolist():
            if status[i] != HIDDEN:
                continue
            for b, j in taken.items():
                if b >= len(blobs) or merged[b] or blobs.areas[b] < MERGE_AREA * cal.area:
                    continue
                if np.linalg.norm(predicted[i] - c[b]) > gates[i]:
                    continue
                pixels, weights = blobs.pixels(b)
                parts = split_blob(pixels, weights, np.array([predicted[j], predicted[i]]))
                quality = float(np.clip(blobs.areas[b] / (2 * cal.area), 0.0, 1.0)) ** 0.5
                for marker, part in ((j, parts[0]), (i, parts[1])):
                    xy[marker] = part
                    status[marker] = MERGED
                    confidence[marker] = quality * MERGED_CONFIDENCE
                merged[b] = True
                break
        return {b for b in taken if b < len(blobs)}

    def _fit_pose(
        self, xy: np.ndarray, confidence: np.ndarray, seen: np.ndarray, status: list[str]
    ) -> Pose | None:
        """The pose from the seen pose markers; markers that sit badly are dropped (hidden)."""
        assert self._pose is not None
        idx = self.pose_markers
        for _ in range(3):
            use = seen[idx]
            if use.sum() < 3:
                return None
            try:
                pose = estimate_pose_2d(
                    self.layout[idx],
                    xy[idx],
                    np.where(use, np.maximum(confidence[idx], 0.05), 0.0),
                    self._pose,
                )
            except ValueError:
                return None
            resid = np.linalg.norm(pose.apply(self.layout[idx])[:, :2] - xy[idx], axis=1)
            bad = use & (resid > POSE_OUTLIER_CM * pose.scale)
            if not bad.any():
                return pose
            worst = idx[np.argmax(np.where(bad, resid, -1.0))]
            logger.debug("pose marker %s sits %.1f px off: dropped", self.names[worst], resid.max())
            seen[worst] = False
            status[worst] = HIDDEN
            confidence[worst] = 0.0
        return None

    def _place_from_landmarks(self, frame_bgr: np.ndarray) -> None:
        """After a long loss: the landmark tracker finds the face, and the layout is placed
        on it (colours stay as calibrated)."""
        self.landmarks.reset()
        lm = self.landmarks.track(frame_bgr)
        if lm is None:
            return
        self.last_landmarks = lm
        pose_v = self.vertices[self.pose_markers]
        try:
            self._pose = estimate_pose_2d(
                self.layout[self.pose_markers], lm.points[pose_v, :2], None, self._pose
            )
        except ValueError:
            return
        self._offset[:] = 0.0
        self._seen[:] = False
        logger.debug("markers lost for %d frames: placed on the face found again", self._lost_for)


def face_clutter(
    frame_bgr: np.ndarray,
    outline_xy: np.ndarray,
    classes: list[ColourClass],
    samples: list[MarkerSample],
) -> list[float]:
    """Per class, the fraction of the face (hull of ``outline_xy`` (n, 2) px) that has the
    class's colour, away from the sampled markers (twice their radius round each)."""
    h, w = frame_bgr.shape[:2]
    lo = np.clip(np.floor(outline_xy.min(axis=0)).astype(int), 0, [w, h])
    hi = np.clip(np.ceil(outline_xy.max(axis=0)).astype(int) + 1, 0, [w, h])
    if (hi - lo < 2).any():
        return [0.0] * len(classes)
    face = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.uint8)
    hull = cv2.convexHull((outline_xy - lo).astype(np.float32)).astype(np.int32)
    cv2.fillConvexPoly(face, hull, 255)
    for s in samples:
        r = int(np.ceil(2 * np.sqrt(s.area / np.pi))) + 1
        c = np.round(s.centroid - lo).astype(int)
        cv2.circle(face, (int(c[0]), int(c[1])), r, 0, -1)
    area = max(int(np.count_nonzero(face)), 1)
    hsv = cv2.cvtColor(frame_bgr[lo[1] : hi[1], lo[0] : hi[0]], cv2.COLOR_BGR2HSV)
    return [
        float(np.count_nonzero(cv2.bitwise_and(class_mask(hsv, c), face))) / area for c in classes
    ]


def lift_points(mesh: FaceMesh, pose: Pose, xy: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """(k, 3) model points where rays through image points ``xy`` (k, 2) meet ``mesh`` under
    ``pose``; a ray that misses gives the mesh vertex ``fallback[i]`` instead."""
    caster = RayCaster(mesh.triangles, mesh.vertices)
    hits = caster.cast(*orthographic_rays(pose, xy))
    out = mesh.vertices[fallback].copy()
    out[hits.hit] = hits.points[hits.hit]
    return out
