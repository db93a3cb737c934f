"""How the person's body moved since the snapshot frame, measured on the body itself.

Corners are picked once in the snapshot frame on the person below the chin (shoulders,
collar, the silhouette's edge against the scene), from the person segmentation both ends
make of that frame (models/person.py). Every frame they are followed straight from the
snapshot frame, so nothing drifts: the frame is first warped back by the last estimate, so
what Lucas-Kanade has left to find is the last frame's small change even after the body has
shrunk by a third (a person leaning back), and a similarity is fitted to where the points
went with RANSAC (a hand over the chest or a point slipping along the scene is outvoted).
Too few points, a motion most of them disagree on, or an implausible one: the last estimate
is kept. The segmentation itself is too slow for every frame (about 10 ms at its 256x144
input, where the whole sender has 16); following points costs about 0.5 ms.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

logger = logging.getLogger(__name__)

#: The body is measured on the frame reduced by a whole factor to about this width, pixels:
#: it is large, and its step on the wire is a pixel of the frame.
WORK_WIDTH = 160
#: Snapshot pixels whose person probability is above this are the person's.
PERSON_THRESHOLD = 0.5
#: The body starts this share of the face's height below the chin (the neck's top follows
#: the head).
BELOW_CHIN = 0.15
#: The person region is grown by this share of the frame's width, so the corners of its
#: silhouette against the scene are picked too.
EDGE_REACH = 0.02
MAX_CORNERS = 60
MIN_INLIERS = 8
#: Least share of the followed points that must agree on the body's motion.
MIN_AGREEMENT = 0.5
#: RANSAC's tolerance, work pixels.
RANSAC_PX = 1.5
#: The body's scale stays within this factor of the snapshot's either way.
MAX_ZOOM = 2.0
LK_WINDOW = 11
_LK_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 20, 0.02)


class BodyTracker:
    """The similarity taking the snapshot frame's body to each later frame's.

    image : (h, w, 3) uint8 BGR snapshot frame; outline : (k, 2) the face outline in it,
    pixels; person : (h, w) float in [0, 1], how likely each pixel shows a person
    """

    def __init__(self, image: np.ndarray, outline: np.ndarray, person: np.ndarray) -> None:
        h, w = image.shape[:2]
        self.reduce = k = max(1, w // WORK_WIDTH)
        # Frame pixels to work pixels (centres kept), and back.
        shift = 0.5 / k - 0.5
        self._to_work = np.array([[1 / k, 0.0, shift], [0.0, 1 / k, shift], [0.0, 0.0, 1.0]])
        self._from_work = np.linalg.inv(self._to_work)
        self._reference = self._gray(image)
        rows, cols = self._reference.shape
        body = cv2.resize(person, (cols, rows), interpolation=cv2.INTER_AREA) > PERSON_THRESHOLD
        below = float(outline[:, 1].max() + BELOW_CHIN * np.ptp(outline[:, 1]))
        top = int(np.clip(np.ceil((below + 0.5) / k - 0.5), 0, rows))  # in work rows
        reach = max(1, round(EDGE_REACH * cols))
        region = cv2.dilate(body.astype(np.uint8), np.ones((2 * reach + 1,) * 2, np.uint8))
        region[:top] = 0
        corners = cv2.goodFeaturesToTrack(
            self._reference,
            MAX_CORNERS,
            qualityLevel=0.01,
            minDistance=max(3, min(rows, cols) // 30),
            mask=region,
        )
        self._points = np.zeros((0, 2), np.float32) if corners is None else corners.reshape(-1, 2)
        #: (3, 3) the last estimate, work pixels (snapshot -> now).
        self._motion = np.eye(3)
        logger.debug("body: %d corners below the chin", len(self._points))

    def _gray(self, image: np.ndarray) -> np.ndarray:
        gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
        k = self.reduce
        if k == 1:
            return gray
        h, w = gray.shape
        return cv2.resize(
            gray[: h - h % k, : w - w % k], (w // k, h // k), interpolation=cv2.INTER_AREA
        )

    @property
    def motion(self) -> np.ndarray:
        """(3, 3) the last estimate: snapshot-frame pixels of the body to this frame's."""
        return self._from_work @ self._motion @ self._to_work

    def update(self, image: np.ndarray) -> np.ndarray:
        """(3, 3) similarity taking the snapshot frame's body pixels to ``image``'s (the
        camera's motion included)."""
        if len(self._points) < MIN_INLIERS:
            return self.motion
        gray = self._gray(image)
        rows, cols = gray.shape
        # ``gray`` seen through the last estimate: the snapshot frame's body where it was.
        back = cv2.warpAffine(
            gray, self._motion[:2], (cols, rows), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
            borderMode=cv2.BORDER_REPLICATE,
        )  # fmt: skip
        moved, status, _ = cv2.calcOpticalFlowPyrLK(
            self._reference,
            back,
            self._points,
            self._points.copy(),  # where the warp back puts them: the start of the search
            winSize=(LK_WINDOW, LK_WINDOW),
            maxLevel=1,  # what is left after the warp back is the last frame's small change
            criteria=_LK_CRITERIA,
            flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
        )
        good = status.ravel() == 1
        if good.sum() < MIN_INLIERS:
            return self.motion
        now = moved[good] @ self._motion[:2, :2].T + self._motion[:2, 2]
        found, inlier = cv2.estimateAffinePartial2D(
            self._points[good], now.astype(np.float32), method=cv2.RANSAC,
            ransacReprojThreshold=RANSAC_PX,
        )  # fmt: skip
        agree = 0 if inlier is None else int(inlier.sum())
        if found is None or agree < max(MIN_INLIERS, MIN_AGREEMENT * int(good.sum())):
            return self.motion
        zoom = float(np.hypot(found[0, 0], found[1, 0]))
        if not 1.0 / MAX_ZOOM <= zoom <= MAX_ZOOM:
            return self.motion
        self._motion = np.vstack([found, [0.0, 0.0, 1.0]])
        return self.motion
