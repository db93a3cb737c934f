"""The sender's measure of the face's edge corrections (models/edge.py).

The receiver's picture around the face is the snapshot frame carried by its surround spline
(models/surround.py), which the sender rebuilds from the values it sends: no drawing, only a
remap of a crop around the face. Near the outline that picture shows the face's edge too (the
spline takes the snapshot's outline to where the face is drawn now), so the optical flow from
the camera's frame to it says how far off the receiver's edge is, at each of the edge points.

A vector is kept only where moving the rebuilt picture by it brings the picture about its
point closer to the frame. Where the scene behind the head changes (carphone's car window),
the flow follows what is not in the snapshot at all: with every vector kept, the call lost
0.012 face SSIM there instead of gaining 0.011 (docs/what-we-tried.md, "The face's edge, sent").
"""

from __future__ import annotations

import cv2
import numpy as np

from facewire.models.edge import EDGE_POINTS, edge_points
from facewire.models.surround import SurroundWarp

#: A face wider than this many pixels is measured on the frame reduced by a whole factor,
#: to between half this and this: a large face costs no more than a small one.
WORK_PX = 96
#: The crop around the face: the outline's box grown by this much of the face's width on each
#: side (room for the flow's smoothing beyond the outline).
MARGIN = 0.35
#: DIS optical flow's preset: the fast one (1.2 ms a frame at 640x480 for the whole measure,
#: against 1.8 with the medium one; face SSIM within 0.006 either way on four clips).
FLOW_PRESET = cv2.DISOPTICAL_FLOW_PRESET_FAST
#: Standard deviation (work pixels) of the Gaussian window about each point: the flow's mean
#: in it is the point's vector (the edge's vectors describe a smooth field, the flow's own
#: noise is finer), and moving the rebuilt picture by it must lower its difference from the
#: frame in that window ...
WINDOW_SIGMA = 3.0
#: ... to this share of what it was: on a scene the snapshot never saw, the flow still finds
#: some match, a few per cent better than none.
KEEP_BELOW = 0.9
#: A vector longer than this share of the face's width is the flow's mismatch, not the edge's
#: error (these are a pixel or two): it is not sent.
MAX_SHIFT = 0.06


class EdgeMeter:
    """Measures the face's edge corrections of one session.

    background : (h, w, 3) uint8, the snapshot frame as the receiver decoded it
    outline : (k, 3) the face's outline in it, as the receiver rebuilds the snapshot's values
    person : (h, w) float, the person mask the receiver makes of it (models.person); None:
        the receiver warps the whole frame
    face_px : the face's width in the snapshot frame, pixels

    A large face is measured on the frame reduced by a whole factor (each work pixel the mean
    of ``reduce`` x ``reduce`` of the frame's), where the receiver's surroundings are rebuilt
    by the same spline on the reduced snapshot frame.
    """

    def __init__(
        self,
        background: np.ndarray,
        outline: np.ndarray,
        person: np.ndarray | None,
        face_px: float,
    ) -> None:
        self.reduce = k = max(1, int(np.ceil(float(face_px) / WORK_PX)))
        # Frame pixels to work pixels (centres kept: x -> (x + 1/2) / k - 1/2), and back.
        shift = 0.5 / k - 0.5
        self._to_work = np.array([[1 / k, 0.0, shift], [0.0, 1 / k, shift], [0.0, 0.0, 1.0]])
        self._from_work = np.linalg.inv(self._to_work)
        h, w = background.shape[:2]
        self.size = (max(1, w // k), max(1, h // k))
        background = self._reduced(background)
        if person is not None:
            person = self._reduced(person.astype(np.float32))
        self.surround = SurroundWarp(background, self._work(outline), person)
        self._flow = cv2.DISOpticalFlow.create(FLOW_PRESET)
        radius = int(np.ceil(3 * WINDOW_SIGMA))
        window = cv2.getGaussianKernel(2 * radius + 1, WINDOW_SIGMA)
        self._weights = (window @ window.T).astype(np.float32)
        self._offsets = np.arange(-radius, radius + 1, dtype=np.float32)

    def _reduced(self, image: np.ndarray) -> np.ndarray:
        """``image`` (a frame, or a crop of one from a multiple of ``reduce``) in work
        pixels: each the mean of reduce x reduce of its pixels."""
        k = self.reduce
        if k == 1:
            return image
        h, w = image.shape[:2]
        whole = image[: h - h % k, : w - w % k]
        return cv2.resize(whole, (w // k, h // k), interpolation=cv2.INTER_AREA)

    def _windows(self, image: np.ndarray, centres: np.ndarray) -> np.ndarray:
        """(EDGE_POINTS, n, n[, c]) float32: the window about each of ``centres`` (work
        pixels, sub-pixel) of ``image``, all in one remap."""
        n = len(self._offsets)
        xs = centres[:, 0, None, None] + self._offsets[None, None, :]
        ys = centres[:, 1, None, None] + self._offsets[None, :, None]
        shape = (len(centres) * n, n)
        mx = np.broadcast_to(xs, (len(centres), n, n)).reshape(shape).astype(np.float32)
        my = np.broadcast_to(ys, (len(centres), n, n)).reshape(shape).astype(np.float32)
        out = cv2.remap(image, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(len(centres), n, n, *out.shape[2:]).astype(np.float32)

    def _work(self, points: np.ndarray) -> np.ndarray:
        """(k, 2 or 3) image points (and depths) in work pixels."""
        out = np.array(points, dtype=np.float64)
        out[:, :2] = out[:, :2] @ self._to_work[:2, :2].T + self._to_work[:2, 2]
        if out.shape[1] > 2:
            out[:, 2] /= self.reduce
        return out

    def measure(
        self,
        image: np.ndarray,
        outline: np.ndarray,
        camera: np.ndarray | None,
        body: np.ndarray | None = None,
    ) -> np.ndarray:
        """(EDGE_POINTS, 2) corrections, pixels: at the edge points of ``outline`` (k, 3), the
        face's outline as the receiver draws it in ``image`` (h, w, 3) BGR, where the frame's
        content sits in the receiver's picture (``camera``: its camera homography; ``body``:
        its body's, models/surround.py)."""
        k = self.reduce
        poly = self._work(outline)
        if camera is not None and k > 1:
            camera = self._to_work @ camera @ self._from_work
        if body is not None and k > 1:
            body = self._to_work @ body @ self._from_work
        vectors = np.zeros((EDGE_POINTS, 2))
        width = float(np.ptp(poly[:, 0]))
        lo = np.floor(poly[:, :2].min(0) - MARGIN * width).astype(int)
        hi = np.ceil(poly[:, :2].max(0) + MARGIN * width).astype(int) + 1
        x0, y0 = max(int(lo[0]), 0), max(int(lo[1]), 0)
        x1, y1 = min(int(hi[0]), self.size[0]), min(int(hi[1]), self.size[1])
        if x1 - x0 < 8 or y1 - y0 < 8:  # the face is (nearly) out of the frame
            return vectors
        crop = image[k * y0 : k * y1, k * x0 : k * x1]
        seen = cv2.cvtColor(self._reduced(crop), cv2.COLOR_BGR2GRAY)
        surroundings = self.surround.warp(poly, camera, (x0, y0, x1, y1), body)
        shown = cv2.cvtColor(surroundings, cv2.COLOR_BGR2GRAY)
        flow = self._flow.calc(seen, shown, np.zeros((*seen.shape, 2), np.float32))
        at = (edge_points(poly) - (x0, y0)).astype(np.float32)
        inside = (at >= 0).all(1) & (at[:, 0] <= x1 - x0 - 1) & (at[:, 1] <= y1 - y0 - 1)
        weights = self._weights[None]
        found = (weights[..., None] * self._windows(flow, at)).sum((1, 2))
        # Kept where moving the rebuilt picture by it brings the window closer to the frame.
        frame = self._windows(seen, at)
        before = (weights * np.abs(frame - self._windows(shown, at))).sum((1, 2))
        after = (weights * np.abs(frame - self._windows(shown, at + found))).sum((1, 2))
        keep = inside & (after < KEEP_BELOW * before)
        # A long vector is the flow's mismatch, not the edge's error.
        keep &= np.hypot(found[:, 0], found[:, 1]) <= MAX_SHIFT * width
        vectors[keep] = found[keep]
        return vectors * k
