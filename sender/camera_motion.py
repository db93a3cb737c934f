"""How the camera moved since the snapshot frame, measured on the background.

Corners are picked once in the snapshot frame, away from the person (the head with a wide
margin, and the body below it) and from anyone the person segmentation finds there. Every
frame they are followed straight from the snapshot frame (no drift from chaining frame to
frame) with pyramidal Lucas-Kanade, starting from where the last estimate put them, and a
similarity is fitted with RANSAC (sent as a homography, so a richer model can come later
without a format change). Points that the person now covers are left out. With too few good
points, or an implausibly large motion, the last estimate is kept. When the points disagree
(a window's moving view, points slipping along a bare wall), so is the last estimate, unless
it is a small motion that a still camera fits as well: then the camera is taken to be still
again. Held for good, such an estimate slid the whole scene of carphone and Claire by 2 px for
the rest of the call (frame SSIM -0.025).
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

logger = logging.getLogger(__name__)

#: The person is the face outline scaled by this much about its centre...
PERSON_REACH = 2.6
#: ... and everything below the chin this many face widths wide.
BODY_WIDTH = 4.0
MAX_CORNERS = 300
MIN_INLIERS = 15
#: Least share of the followed points that must agree on the camera's motion.
MIN_AGREEMENT = 0.6
RANSAC_PX = 2.0
#: A motion held whose frame corners move at most this far (px) is let go when a still
#: camera fits the points as well: a shake seen once, or points slipping along a bare wall.
SMALL_PX = 2 * RANSAC_PX
#: No frame corner moves by more than this fraction of the frame's size.
MAX_SHIFT = 0.15
#: Snapshot pixels whose person probability (models.person) is above this are nobody's
#: background: a second person moving would pass for the camera.
PEOPLE_THRESHOLD = 0.2
LK_WINDOW = 21
#: The points are followed in the frames scaled down to at most this many pixels on their
#: longer side: building the two frames' pyramids took most of the time, and grew with the
#: frame (2.4 ms at 1280x720 on one core, loaded); a camera's shake is measured to a tenth of
#: a pixel there, a fifth of the channel's step.
FOLLOW_SIDE = 640
_LK_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)


def _person_parts(outline: np.ndarray) -> tuple[np.ndarray, tuple[float, float, float]]:
    """Where the person may be, given the face outline (k, 2) in pixels: the head, a convex
    polygon (m, 2), and the body below the chin, shoulders and arms reaching BODY_WIDTH face
    widths out: (x0, x1, y0), everything right of x0, left of x1 and below y0."""
    centre = outline.mean(0)
    head = centre + PERSON_REACH * (outline - centre)
    hull = cv2.convexHull(head.astype(np.float32)).reshape(-1, 2)
    half = BODY_WIDTH * np.ptp(outline[:, 0]) / 2
    return hull, (centre[0] - half, centre[0] + half, float(outline[:, 1].max()))


def person_mask(shape: tuple[int, int], outline: np.ndarray) -> np.ndarray:
    """(h, w) bool: where the person may be, given the face outline (k, 2) in pixels."""
    h, w = shape
    hull, (bx0, bx1, by0) = _person_parts(outline)
    mask = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 1)
    x0, x1 = int(max(0, bx0)), int(min(w, bx1 + 1))
    mask[int(np.clip(by0, 0, h)) :, x0:x1] = 1
    return mask.astype(bool)


def person_covers(points: np.ndarray, outline: np.ndarray) -> np.ndarray:
    """(n,) bool: which of ``points`` (n, 2) :func:`person_mask` covers (to within its
    rounding to pixels), found without drawing the frame's mask."""
    hull, (bx0, bx1, by0) = _person_parts(outline)
    # Inside a convex polygon: on the same side of every edge.
    edges = np.roll(hull, -1, axis=0) - hull
    offsets = points[:, None, :] - hull[None]
    cross = edges[None, :, 0] * offsets[:, :, 1] - edges[None, :, 1] * offsets[:, :, 0]
    head = (cross >= 0).all(1) | (cross <= 0).all(1)
    body = (points[:, 0] >= bx0) & (points[:, 0] <= bx1) & (points[:, 1] >= by0)
    return head | body


class CameraTracker:
    """Homography from the snapshot frame to each later frame, from the background.

    image : (h, w, 3) uint8 BGR snapshot frame; outline : (k, 2) face outline in it, pixels;
    people : optional (h, w) float, how likely each pixel shows a person (models.person)
    """

    def __init__(
        self, image: np.ndarray, outline: np.ndarray, people: np.ndarray | None = None
    ) -> None:
        reference = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        shape = reference.shape
        self._scale = min(1.0, FOLLOW_SIDE / max(shape))
        self._reference = self._followed(reference)
        nobody = ~person_mask(shape, outline)
        if people is not None:
            # Grown by half the LK window: a corner whose window reaches into a person that
            # moves on their own is pulled along.
            anyone = (people > PEOPLE_THRESHOLD).astype(np.uint8)
            nobody &= ~cv2.dilate(anyone, np.ones((LK_WINDOW, LK_WINDOW), np.uint8)).astype(bool)
        background = nobody.astype(np.uint8)
        side = min(shape)
        corners = cv2.goodFeaturesToTrack(
            reference,
            MAX_CORNERS,
            qualityLevel=0.01,
            minDistance=max(4, side // 40),
            mask=background,
        )
        self._points = np.zeros((0, 2), np.float32) if corners is None else corners.reshape(-1, 2)
        self.homography = np.eye(3)
        self.inliers = len(self._points)
        logger.debug("camera: %d background corners", len(self._points))

    def update(self, image: np.ndarray, outline: np.ndarray | None) -> np.ndarray:
        """(3, 3) homography taking snapshot-frame pixels of the background to ``image``'s.

        ``outline`` is the face outline in ``image`` (None when no face was found).
        """
        return self.settle(image.shape, outline, self.follow(image))

    def follow(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Where the background's corners are in ``image``: (moved (n, 2) frame pixels, found
        (n,) bool), or None with too few corners. Needs no face, so the sender follows them
        while its tracker looks for the face (sender/encoder.py); :meth:`settle` takes it."""
        if len(self._points) < MIN_INLIERS:
            return None
        gray = self._followed(cv2.cvtColor(image, cv2.COLOR_BGR2GRAY))
        guess = cv2.perspectiveTransform(self._points[None], self.homography)[0]
        moved, status, _ = cv2.calcOpticalFlowPyrLK(
            self._reference,
            gray,
            self._to_followed(self._points),
            self._to_followed(guess),
            winSize=(LK_WINDOW, LK_WINDOW),
            maxLevel=3,
            criteria=_LK_CRITERIA,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        moved = (moved + 0.5) / np.float32(self._scale) - 0.5
        return moved, status.ravel() == 1

    def settle(
        self,
        shape: tuple[int, ...],
        outline: np.ndarray | None,
        followed: tuple[np.ndarray, np.ndarray] | None,
    ) -> np.ndarray:
        """:meth:`update` of a frame of ``shape`` whose corners were :meth:`follow`-ed."""
        if followed is None:
            return self.homography
        moved, good = followed
        if outline is not None:
            good = good & ~person_covers(moved, outline)
        if good.sum() < MIN_INLIERS:
            return self.homography
        # A similarity (shift, roll, zoom): what a shaking camera does to the scene, and few
        # enough degrees of freedom that a moving scene seen through a window cannot bend it.
        found, inlier = cv2.estimateAffinePartial2D(
            self._points[good], moved[good], method=cv2.RANSAC, ransacReprojThreshold=RANSAC_PX
        )
        # The scene must agree on one motion: when most points disagree (another person or
        # a window's view moving), no new motion is trusted.
        agree = 0 if inlier is None else int(inlier.sum())
        if found is None or agree < max(MIN_INLIERS, MIN_AGREEMENT * int(good.sum())):
            # Nor is a small motion held, once a still camera fits the points as well: a shake
            # seen once, or points slipping along a bare wall, must not shift the scene for
            # the rest of the call.
            small = self._corner_shift(self.homography, shape) <= SMALL_PX
            still = self._support(np.eye(3), good, moved)
            if small and still >= self._support(self.homography, good, moved):
                self.homography = np.eye(3)
            return self.homography
        homography = np.vstack([found, [0.0, 0.0, 1.0]])
        h, w = shape[:2]
        if self._corner_shift(homography, shape) > MAX_SHIFT * max(h, w):
            return self.homography  # implausible for a camera shaking: keep the last one
        self.homography = homography
        self.inliers = int(inlier.sum())
        return self.homography

    def _followed(self, gray: np.ndarray) -> np.ndarray:
        """``gray`` at the size the points are followed in."""
        if self._scale >= 1.0:
            return gray
        h, w = gray.shape
        size = (round(w * self._scale), round(h * self._scale))
        return cv2.resize(gray, size, interpolation=cv2.INTER_AREA)

    def _to_followed(self, points: np.ndarray) -> np.ndarray:
        """(n, 2) float32 frame pixels in the picture followed (pixel centres kept)."""
        return ((points + 0.5) * self._scale - 0.5).astype(np.float32)

    def _support(self, homography: np.ndarray, good: np.ndarray, moved: np.ndarray) -> int:
        """How many of the followed points ``homography`` puts within RANSAC_PX of where
        they were found."""
        where = cv2.perspectiveTransform(self._points[good][None], homography)[0]
        return int((np.linalg.norm(where - moved[good], axis=1) <= RANSAC_PX).sum())

    @staticmethod
    def _corner_shift(homography: np.ndarray, shape: tuple[int, ...]) -> float:
        """The most any corner of a frame of ``shape`` moves under ``homography``, px."""
        h, w = shape[:2]
        corners = np.array([[0, 0, 1], [w - 1, 0, 1], [w - 1, h - 1, 1], [0, h - 1, 1]], float)
        moved = corners @ homography.T
        return float(np.abs(moved[:, :2] / moved[:, 2:3] - corners[:, :2]).max())
