"""Something in front of the face (a hand, a cup, a pen): where, so it is sent over the face.

The receiver draws the face from the snapshot's texture over everything, so a hand held in
front of the face never shows: the refreshes (sender/refresh.py) show what the model misses
only around the face. Looked for in the texture, where the face holds still: the frame is
unwrapped through the mesh as the receiver draws it, at :data:`SIDE` texels, and compared in
blocks with the snapshot's texture (less their median difference: the light) and with the
unwrap of the measurement before, leaving out the eyes and the mouth (the REM patches' own)
and texels seen edge-on.

How far the face is from its snapshot tells no hand apart: a turn takes parts of Claire's
face 66 grey levels from it, foreman's 160, where akiyo's cheek under a flag is 55-65
(docs/what-we-tried.md, "A hand in front of the face"). What tells it is its coming: within a
measurement (four frames) a block changes by more than :data:`ONSET` while the head holds
its place, and is then far from the snapshot. Such blocks are covered until they are near
the snapshot again; their place in the frame, grown a little, is what is sent over the face.
"""

from __future__ import annotations

import cv2
import numpy as np

from facewire.sender.texture import UvRasteriser

#: The texture the face is compared in, texels on a side ...
SIDE = 64
#: ... in blocks of this many texels on a side.
BLOCK = 8
#: A block changed by more than this (mean absolute luma difference, 0-255) within one
#: measurement has something coming in front of it (ordinary talking heads: at most 35-49) ...
ONSET = 45.0
#: ... and stays covered while it differs from the snapshot by more than this.
COVERED = 30.0
#: Texels on triangles seen more obliquely than this cosine take no part.
MIN_FACING = 0.3
#: Blocks with fewer seen texels than this share take no part.
MIN_SEEN = 1 / 3
#: Which texels something else of the face hides is found on the face scaled to at most this
#: many pixels wide (twice the texture's side).
HIDDEN_WIDTH = 2 * SIDE
#: The covered blocks' place in the frame is grown by this share of its size each way.
GROW = 0.25


class FaceOcclusion:
    """Where something stands in front of the face, measurement by measurement.

    triangles, uvs : the face mesh's; texture : (T, T, 3) uint8 BGR, the snapshot's texture as
    the receiver decoded it; left_out : (T, T) bool, texels not looked at (the eyes and the
    mouth, which the REM patches show as they are)
    """

    def __init__(
        self, triangles: np.ndarray, uvs: np.ndarray, texture: np.ndarray, left_out: np.ndarray
    ) -> None:
        self._rasteriser = UvRasteriser(triangles, uvs, SIDE)
        small = cv2.resize(texture, (SIDE, SIDE), interpolation=cv2.INTER_AREA)
        self._reference = cv2.cvtColor(small, cv2.COLOR_BGR2GRAY).astype(np.float32)
        out = cv2.resize(left_out.astype(np.uint8), (SIDE, SIDE), interpolation=cv2.INTER_AREA)
        self._looked = cv2.erode((out == 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        self._last: np.ndarray | None = None
        self._covered = np.zeros((SIDE // BLOCK, SIDE // BLOCK), bool)
        # Which block each covered texel lies in (raster order, as texel_positions gives them).
        index = self._rasteriser.covered_index
        self._block_of = (index // SIDE // BLOCK) * (SIDE // BLOCK) + (index % SIDE) // BLOCK

    def update(
        self, image: np.ndarray, vertices: np.ndarray, still: bool
    ) -> tuple[int, int, int, int] | None:
        """The area (x, y, width, height, frame pixels) of what is in front of the face in
        ``image`` (h, w, 3) BGR, the face drawn at ``vertices`` (n, 3) image space; None when
        nothing is. ``still``: whether the head held its place since the last measurement
        (a block's change is then no turn of it)."""
        # What is hidden behind the nose, found on the face scaled to about HIDDEN_WIDTH
        # pixels: at the frame's own size that z-buffer took 16 ms at 640x480 (the sender's
        # p90 frame 27 ms against 11), for a texture of SIDE texels.
        width = float(np.ptp(np.asarray(vertices)[:, 0]))
        scale = min(1.0, HIDDEN_WIDTH / width) if width > 0 else 1.0
        texture, valid = self._rasteriser.sample(image, vertices, MIN_FACING, hidden_scale=scale)
        luma = cv2.cvtColor(texture, cv2.COLOR_BGR2GRAY).astype(np.float32)
        seen = valid & self._looked
        if seen.sum() < BLOCK * BLOCK:
            self._last, self._covered[:] = None, False
            return None
        light = float(np.median(luma[seen] - self._reference[seen]))
        far = _blocks(np.abs(luma - self._reference - light), seen)
        if self._last is not None and still:
            came = _blocks(np.abs(luma - self._last), seen) > ONSET
            self._covered |= came & (far > COVERED)
        self._covered &= far > COVERED
        self._last = luma
        if not self._covered.any():
            return None
        points, _ = self._rasteriser.texel_positions(vertices)
        inside = self._covered.ravel()[self._block_of]
        xy = points[inside, :2]
        lo, hi = xy.min(0), xy.max(0)
        grow = GROW * (hi - lo) + 2.0
        h, w = image.shape[:2]
        x0, y0 = np.floor(np.maximum(lo - grow, 0)).astype(int)
        x1, y1 = np.ceil(np.minimum(hi + grow, (w, h))).astype(int)
        if x1 <= x0 or y1 <= y0:
            return None
        return int(x0), int(y0), int(x1 - x0), int(y1 - y0)


def _blocks(diff: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """(SIDE / BLOCK, SIDE / BLOCK) mean of ``diff`` over each block's seen texels (0 where a
    block has fewer than MIN_SEEN of them seen)."""
    n = SIDE // BLOCK
    weight = seen.astype(np.float32).reshape(n, BLOCK, n, BLOCK).sum(axis=(1, 3))
    total = np.where(seen, diff, 0.0).reshape(n, BLOCK, n, BLOCK).sum(axis=(1, 3))
    mean = total / np.maximum(weight, 1.0)
    return np.where(weight >= MIN_SEEN * BLOCK * BLOCK, mean, 0.0)
