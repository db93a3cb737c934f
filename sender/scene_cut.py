"""Whether the camera now shows another scene: a cut, a switched camera, another person.

The receiver draws every frame from the session's snapshot frame: after a cut it would draw
the old scene with the tracked face wherever the new shot puts one. So the sender starts a
new session there (a new snapshot), and needs to know when.

A cut changes the whole frame at once, which no motion of a talking head does: between two
consecutive frames both the colour histogram (Bhattacharyya distance of 8x8x8 BGR bins, on a
64x48 thumbnail) and a 16x12 grey thumbnail (mean absolute difference, grey levels) change by
more than their thresholds. Over 18 real clips (talking heads, a pan, a woman signing, a
news studio whose monitor changes, 300 frames each) consecutive frames stayed under 0.20 and
15 (foreman's fast pan: 0.14 and 14.7; news' monitor: 0.30 and 10.7); the first frames of two
different clips were at least 0.43 and 23 apart (BENCHMARKS.md, "A new picture when the
scene changes").

A dissolve changes the frame as slowly as a talking head does, and ends in another scene: a
frame whose colours are DRIFT_HISTOGRAM apart from the session's snapshot frame (and its grey
thumbnail THUMBNAIL_CUT apart) for DRIFT_S is another scene too. Over the 19 real clips the
frames of one shot stayed under 0.39 from their first (carphone's window and light); the
first frames of two different clips are 0.57 apart and more.

A face that jumps farther than a face width from one frame to the next, or grows or shrinks
by half, is another face (a person who sat down as the other left, a camera switched to a
similar scene): no head moves that much in a frame.

The same face seen far better than in its session's snapshot frame is a new scene too: a
snapshot taken in profile has no texture for the far side of the face, and the face turned
to the camera later was drawn from the hole-filling, smeared (mad900, a mother looking at
her daughter at the call's start; paris). :class:`BetterView` says when.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Both must be passed between two consecutive frames for a cut.
HISTOGRAM_CUT = 0.25
THUMBNAIL_CUT = 16.0
#: A frame this far in colours from the session's snapshot frame, for DRIFT_S running, is
#: another scene (a dissolve).
DRIFT_HISTOGRAM = 0.5
DRIFT_S = 0.5
#: A face's centre moving this many face widths in one frame is another face...
FACE_JUMP = 1.0
#: ...and so is one whose width changes by this factor (either way).
FACE_RESIZE = 1.5

#: The face is seen better than at its snapshot when the share of it turned to the camera
#: (FaceMesh.facing_share) is at least BETTER_SHARE more than the snapshot frame's, and at
#: least FRONTAL_SHARE (a face looking into the camera shows 0.82-0.92 of itself, one in
#: profile 0.53-0.6), ...
BETTER_SHARE = 0.1
FRONTAL_SHARE = 0.8
#: ... for BETTER_FRAMES frames running (a turn that passes through frontal is no view to
#: keep), from BETTER_AFTER_S seconds after the session began.
BETTER_FRAMES = 10
BETTER_AFTER_S = 1.0
#: The face is seen better, too, when it is this many times as wide as in the snapshot frame
#: and wider than the snapshot's texture is sharp for, or this many of its snapshot's widths
#: from where the snapshot saw it (BetterView; talking heads move at most 0.6 of one).
GROWN = 1.5
MOVED = 1.0
#: The face is seen better, too, when its eyes are open where the snapshot's were shut or
#: cast down (a call begun looking at the keyboard: that texture's lids, and the face pitched
#: down with them, stayed for the whole call): the lids' gap per eye width
#: (:func:`eye_openness`) at least EYES_OPENED times the snapshot's and at least OPEN_EYES.
#: The tracker's lids on the real clips: open 0.25-0.4, shut or cast down 0.05-0.13 (akiyo
#: reads her papers for most of her clip, 0.07-0.08; her first frame looks up, 0.38).
EYES_OPENED = 2.0
OPEN_EYES = 0.2
#: (upper lid, lower lid, corner, corner) of each eye among the face's 468 landmarks.
_EYES = ((159, 145, 33, 133), (386, 374, 362, 263))

#: A scene with no face to draw gets a session without one (its face kept outside the frame,
#: the scene drawn from its own snapshot frame): a new scene that shows no face NO_FACE_AFTER_S
#: after its cut (a shot of a room, a slide; a flash or a hand over the lens is over by then),
#: or a face lost for FACE_LOST_S (the person left, the camera turned away: the face would be
#: drawn where it was, over the scene as it was). In such a session a face tracked in
#: FACE_FOUND_FRAMES frames running begins a session of it.
NO_FACE_AFTER_S = 0.3
FACE_LOST_S = 1.0
FACE_FOUND_FRAMES = 5

#: A frame's colour histogram and grey thumbnail.
Features = tuple[np.ndarray, np.ndarray]

_HIST_SIZE = (64, 48)
_GREY_SIZE = (16, 12)


def _features(image: np.ndarray) -> Features:
    # The thumbnails are turned the way the frame is: a 720x1280 phone frame then shrinks by
    # whole factors, which INTER_AREA does in 0.3 ms where 64x48 took 1.8.
    upright = image.shape[0] > image.shape[1]
    small = cv2.resize(
        image, _HIST_SIZE[::-1] if upright else _HIST_SIZE, interpolation=cv2.INTER_AREA
    )
    hist = cv2.calcHist([small], [0, 1, 2], None, [8, 8, 8], [0, 256] * 3)
    cv2.normalize(hist, hist, 1.0, 0.0, cv2.NORM_L1)
    grey = cv2.resize(
        small, _GREY_SIZE[::-1] if upright else _GREY_SIZE, interpolation=cv2.INTER_AREA
    )
    return hist, cv2.cvtColor(grey, cv2.COLOR_BGR2GRAY).astype(np.float32)


def face_box(points: np.ndarray) -> tuple[float, float, float]:
    """(centre x, centre y, width) of a tracked face, (n, 2+) image pixels."""
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    lo, hi = xy.min(0), xy.max(0)
    return float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2), float(hi[0] - lo[0])


def eye_openness(points: np.ndarray) -> float:
    """The lids' gap over the eye's width, both eyes' mean, of a tracked face ((468, 2+)
    image pixels)."""
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    gaps = [float(np.linalg.norm(xy[up] - xy[down])) for up, down, _, _ in _EYES]
    widths = [max(float(np.linalg.norm(xy[a] - xy[b])), 1e-9) for _, _, a, b in _EYES]
    return float(np.mean(np.divide(gaps, widths)))


def another_face(before: tuple[float, float, float], now: tuple[float, float, float]) -> bool:
    """Whether the face boxes (:func:`face_box`) of two consecutive frames are two faces."""
    (x0, y0, w0), (x1, y1, w1) = before, now
    if min(w0, w1) <= 0:
        return False
    moved = np.hypot(x1 - x0, y1 - y0) / max(w0, w1)
    return bool(moved > FACE_JUMP or max(w0, w1) / min(w0, w1) > FACE_RESIZE)


class SceneCut:
    """Looks at every frame; :meth:`changed` is True on the first frame of another scene.
    ``fps``: frames a second (how long a dissolve's end is waited for)."""

    def __init__(self, fps: float = 30.0) -> None:
        #: The features of the last frame and of the one before it (None: not seen yet); at a
        #: dissolve's end, ``before`` is the snapshot frame's (the scene left).
        self.last: Features | None = None
        self.before: Features | None = None
        #: The cuts seen so far (frames of another scene).
        self.cuts = 0
        self._snapshot: Features | None = None  # the session's snapshot frame's features
        self._drift_frames = max(1, round(DRIFT_S * fps))
        self._drifted = 0  # frames running far from the snapshot frame

    def begin(self, image: np.ndarray) -> None:
        """A session begins from ``image``: what a dissolve is measured from (and, at the
        first, the frame the next one is told from)."""
        self._snapshot, self._drifted = _features(image), 0
        if self.last is None:
            self.last = self._snapshot

    def changed(self, image: np.ndarray) -> bool:
        """Whether ``image`` (h, w, 3) uint8 BGR shows another scene than the frame before
        (a cut), or than the session's snapshot frame for a while (a dissolve's end)."""
        self.before, self.last = self.last, _features(image)
        if self.before is not None and _apart(self.before, self.last):
            self.cuts += 1
            return True
        if self._snapshot is not None and _apart(self._snapshot, self.last, DRIFT_HISTOGRAM):
            self._drifted += 1
            if self._drifted == self._drift_frames:
                self.before = self._snapshot
                self.cuts += 1
                return True
        else:
            self._drifted = 0
        return False

    def like(self, features: Features) -> bool:
        """Whether the last frame shows the scene of a frame's ``features`` (:attr:`last`)."""
        return self.last is not None and not _apart(features, self.last)


def _apart(a: Features, b: Features, colours_apart: float = HISTOGRAM_CUT) -> bool:
    """Whether two frames' features (:func:`_features`) are two scenes': their colours more
    than ``colours_apart`` apart and their layouts more than THUMBNAIL_CUT."""
    colours = cv2.compareHist(a[0], b[0], cv2.HISTCMP_BHATTACHARYYA)
    layout = float(np.abs(a[1] - b[1]).mean())
    return bool(colours > colours_apart and layout > THUMBNAIL_CUT)


class BetterView:
    """Whether a session's face is now seen far better than in its snapshot frame: far more
    of it, with its eyes open where the snapshot's were shut (a call begun looking down), far
    larger than its texture is sharp for (a person who leans in), or far from where the
    snapshot saw it (a person who walked: the snapshot's body stays where it was, and the
    head's surroundings tear as the warp drags them).

    share : the snapshot frame's FaceMesh.facing_share; box : its face_box; fps : frames a
    second; sharp_up_to : the face's width beyond which the snapshot's texture holds less than
    the camera sees (infinite: the largest texture there is). A face past it counts once it is
    also GROWN times the snapshot's: a texture sized at the least a face needs is past it
    whenever the head comes a little closer. eyes : the snapshot's eye_openness (None: the
    eyes are not looked at)."""

    def __init__(
        self,
        share: float,
        box: tuple[float, float, float],
        fps: float,
        sharp_up_to: float = float("inf"),
        eyes: float | None = None,
    ) -> None:
        self.share, self.box, self.eyes = share, box, eyes
        self.sharp_up_to = max(sharp_up_to, GROWN * box[2])
        self._wait = round(BETTER_AFTER_S * fps)  # frames before a view counts
        self._better = 0  # frames running with a better view

    def seen(
        self, share: float, box: tuple[float, float, float], eyes: float | None = None
    ) -> bool:
        """Take a frame's facing share, face box and eye openness; True (once) when a new
        snapshot is due."""
        self._wait -= 1
        more = share >= max(self.share + BETTER_SHARE, FRONTAL_SHARE)
        (x0, y0, w0), (x, y, w) = self.box, box
        moved = np.hypot(x - x0, y - y0) > MOVED * w0
        opened = (
            self.eyes is not None
            and eyes is not None
            and eyes >= max(EYES_OPENED * self.eyes, OPEN_EYES)
            and share >= FRONTAL_SHARE
        )
        good = more or w > self.sharp_up_to or moved or opened
        self._better = self._better + 1 if good else 0
        if self._wait > 0 or self._better < BETTER_FRAMES:
            return False
        self._better, self._wait = 0, 1 << 30  # once: the new session has its own
        return True
