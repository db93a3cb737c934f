"""The region around the face (hair, ears, neck) carried by the head's motion.

The face mesh covers only the face oval. Everything else the receiver shows comes from the
snapshot frame (its background image, with the face filled in). Left still, that frame shows
hair and ears frozen while the face slides over them, and the filled-in face where the head
used to be. Instead, every frame warps the snapshot frame with a thin-plate spline:

- inner ring: the face outline (the mesh's boundary loop) goes from where it was in the
  snapshot frame to where the rendered face puts it now, so the filled-in face stays under the
  rendered one and no hole opens;
- head ring: the outline scaled about its centre by ``HEAD_REACH`` (hair, ears, chin) moves
  as a rigid part of the head: each of its points sits at the depth of its outline point, and
  the 3D similarity (rotation, scale, shift) that best maps the old outline's upper part (the
  jaw moves on its own) to the new one carries it. A head turning away carries its hair
  round with it; a 2D similarity fitted to the outline's narrowing took the turn for a roll
  and a shrink, and stretched the hair above into a cone. Below the mouth the ring moves
  less, fading to ``NECK_FOLLOW`` at the bottom, so the neck bends instead of the shoulders
  flying with the head;
- still ring (the outline scaled by ``STILL_REACH``): stays put, and the head's part of the
  warp fades out just beyond it, so the background stays where the camera sees it. A camera
  homography, when given, moves the whole scene.

Given a person mask of the snapshot frame (``facewire.receiver.person``), only the person is warped
this way. The scene behind is the snapshot frame with the person painted out, moved by the
camera alone, so walls and windows near a moving head stay straight. Where the person has
moved away, that painted-out scene shows. Then nothing holds the top of the head back: the
still ring above the eyes moves with the head as the head ring does, so the hair goes
wherever the head goes. Held still instead, a head that shrinks (a person leaning back)
pulled its hair into streaks up to the still ring, and past the frame's top edge the warp's
reflected border mirrored hair into them. What the person layer would take from above the
snapshot frame, or beside it, is not the person's: the source is padded with the frame's
reflection, whose person layer is empty there, and the scene shows (a shoulder cut by the
side may end in a straight edge; carried on, it went on to the frame's edge where the camera
showed it ending, and mirrored it came back as a second shoulder). Below the frame it is: a
body cut by the frame's bottom edge goes straight on past it, so a body that shrinks
(models/body.py) still reaches the bottom.

The rest of the person (shoulders, chest, arms) moves by the body's own similarity when one
is given (``body``: the person's pixels from the snapshot frame to this one, camera
included): the still ring's points below the mouth and the neck's share of the head ring go
with it instead of the camera, and so does the person layer beyond the head's reach. Where
the body moved away the painted-out scene shows.

The spline maps each output pixel back to the snapshot pixel it shows (a backward map), solved
per frame with its centres at the current control points (of two that would fold it, a ring's
point following the head carried onto one held still, the less important left out), evaluated
on a coarse grid and interpolated to full size for ``cv2.remap``.
"""

from __future__ import annotations

import logging

import cv2
import numpy as np

from facewire.models.fill import fill_invalid
from facewire.models.thin_plate import ThinPlate, squared_distances

logger = logging.getLogger(__name__)

#: Head ring = face outline scaled about its centre by this much (takes in hair and ears).
HEAD_REACH = 1.4
#: Still ring = face outline scaled by this much: the background beyond it does not follow
#: the head (a spline with only the frame's border held would bend the whole scene).
STILL_REACH = 2.4
#: How much of the head's motion the bottom of the head ring (under the chin) follows.
NECK_FOLLOW = 0.5
#: The mouth's line: the outline's centre and this share of the way down to its lowest point.
#: The head's motion is fitted above it (the jaw moves on its own).
MOUTH_LINE = 0.35
#: Beyond the still ring the head's part of the warp eases to nothing by this many times
#: the ring's radius.
FADE = 1.3
#: The spline is evaluated every GRID_STEP pixels and interpolated in between.
GRID_STEP = 16
#: Tikhonov regulariser of the spline (pixels^2): keeps nearly coincident controls stable.
SMOOTHING = 1e-3
#: Of two controls closer than this many times the difference of their displacements, the
#: less important one is left out: where the difference reaches the distance the spline folds
#: (output pixels on both sides show one snapshot pixel, and what lay between is torn open).
UNFOLD = 1.0
#: Where the segmentation's probability is above this, the pixel is the person's. Low: a
#: hat or hair half taken for scene tears when the head moves, and a body that leans back
#: leaves its doubtful edges behind (docs/what-we-tried.md, "The streak above the head").
PERSON_THRESHOLD = 0.2
#: The person layer reaches this fraction of the frame's width beyond the person mask, and
#: its edge fades over as much again. The scene is painted out only inside that reach,
#: so a frame with no motion comes out exactly as the snapshot. About a pixel of the
#: segmentation (256 wide): what the reach takes in of the scene moves with the person, and
#: at twice this the shelves and posters beside a moving head or shoulder were dragged along.
PERSON_MARGIN = 0.005
#: The scene behind the person is filled in at most this many pixels wide, then scaled up.
FILL_WIDTH = 160
#: The warp's source is the snapshot frame padded by 1/SOURCE_PAD of its longer side.
SOURCE_PAD = 4
#: Lines at a frame's edge that differ from the line inside them as no scene does (the black
#: column of an analogue capture, a dark last row an encoder left) are the camera's border,
#: not the scene: looked for within the outermost max(BORDER_MIN, side // BORDER_SHARE) lines,
#: where one differs from the next line in by more than BORDER_RATIO times the typical
#: difference of neighbouring lines further in, and by BORDER_STEP grey levels more.
BORDER_MIN, BORDER_SHARE = 4, 64
BORDER_RATIO, BORDER_STEP = 3.0, 15.0
#: A black bar at the edge is border too, however deep (a letterbox; bowing's 15 blank lines
#: above the picture, pulled down by the head as a black wedge above it when he bowed): the
#: outermost lines, up to 1/BAR_SHARE of the side, whose median is under BAR_MEDIAN grey levels
#: and three quarters under BAR_LEVEL (a few bright specks allowed: a tape's head-switching
#: line). The lines just inside it are then looked at as above.
BAR_MEDIAN, BAR_LEVEL, BAR_SHARE = 16.0, 32.0, 8


def similarity_3d(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """(rotation (3, 3), scale, shift (3,)): the least-squares similarity taking ``src`` to
    ``dst``, both (k, 3) (Umeyama 1991). Points all in one plane give that plane's 2D
    similarity."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    u, sigma, vt = np.linalg.svd(b.T @ a / len(src))
    sign = np.ones(3)
    sign[2] = -1.0 if np.linalg.det(u @ vt) < 0 else 1.0  # a proper rotation, not a mirror
    spread = float((a**2).sum()) / len(src)
    if spread <= 0:  # all points together: follow their centre only
        return np.eye(3), 1.0, mu_d - mu_s
    rotation = (u * sign) @ vt
    scale = float((sigma * sign).sum()) / spread
    return rotation, scale, mu_d - scale * rotation @ mu_s


def _in_space(outline: np.ndarray) -> np.ndarray:
    """(k, 3) float64 outline points from (k, 3), or (k, 2) taken at depth 0."""
    points = np.asarray(outline, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise ValueError(f"expected a (k, 2) or (k, 3) outline, got {points.shape}")
    return points if points.shape[1] == 3 else np.c_[points, np.zeros(len(points))]


def _is_still(camera: np.ndarray | None) -> bool:
    """Whether the camera homography moves nothing (None, or the identity to rounding)."""
    return camera is None or np.allclose(camera, np.eye(3), rtol=0.0, atol=1e-12)


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(3, 3) homography applied to (k, 2) points."""
    h = np.c_[points, np.ones(len(points))] @ matrix.T
    return h[:, :2] / h[:, 2:3]


class SurroundWarp:
    """Warps the snapshot frame so the head's surroundings follow the face.

    background : (h, w, 3) uint8, the snapshot frame
    outline : (k, 3) float, image space (pixels; z away from the camera): the face outline
        (mesh boundary loop) where the snapshot frame shows it; (k, 2) for a flat one
    person : optional (h, w) float in [0, 1], where the snapshot frame shows a person. Without
        it the whole frame is warped.
    """

    def __init__(
        self, background: np.ndarray, outline: np.ndarray, person: np.ndarray | None = None
    ) -> None:
        self._outline3 = _in_space(outline)
        if len(self._outline3) < 3:
            raise ValueError(f"expected an outline of 3 points or more, got {outline.shape}")
        self.background = background
        self.height, self.width = background.shape[:2]
        self.outline = outline = self._outline3[:, :2]
        centre = outline.mean(0)
        self._head = centre + HEAD_REACH * (outline - centre)
        self._still = (centre + STILL_REACH * (outline - centre))[::2]
        # 1 above the mouth, fading to NECK_FOLLOW at the ring's lowest point.
        bottom = self._head[:, 1].max()
        mouth = mouth_line(outline)
        fade = np.clip((self._head[:, 1] - mouth) / max(bottom - mouth, 1e-6), 0.0, 1.0)
        self._follow = 1.0 - (1.0 - NECK_FOLLOW) * fade
        # The head's motion is fitted on the outline above the mouth; the ring's points sit
        # at their outline points' depth.
        upper = outline[:, 1] <= mouth
        self._upper = upper if upper.sum() >= 3 else np.ones(len(outline), bool)
        self._head3 = np.c_[self._head, self._outline3[:, 2]]
        self._still3 = np.c_[self._still, self._outline3[::2, 2]]
        # With a person layer the still ring follows the head above the eyes, fading to still
        # at the mouth (the shoulders below stay); without one it holds the scene in place.
        self._still_follow = np.zeros(len(self._still))
        if person is not None:
            eyes = centre[1]
            self._still_follow = np.clip(
                (mouth - self._still[:, 1]) / max(mouth - eyes, 1e-6), 0.0, 1.0
            )
        # Which controls give way when two would fold the warp: the outline first, then the
        # head ring, then the still ring, its points that follow the head before those held.
        still_first = np.argsort(-self._still_follow, kind="stable")
        n = len(outline)
        self._rank = np.empty(2 * n + len(self._still), int)
        self._rank[np.r_[np.arange(2 * n), 2 * n + still_first]] = np.arange(len(self._rank))
        # Grid nodes where cv2.resize by GRID_STEP samples them ((j + 0.5) * step - 0.5), so
        # resizing the coarse map is exact bilinear interpolation between nodes.
        nx, ny = -(-self.width // GRID_STEP), -(-self.height // GRID_STEP)
        xs = (np.arange(nx) + 0.5) * GRID_STEP - 0.5
        ys = (np.arange(ny) + 0.5) * GRID_STEP - 0.5
        gx, gy = np.meshgrid(xs, ys)
        self._grid = np.c_[gx.ravel(), gy.ravel()]
        self._grid_shape = gy.shape
        self._reach = reach_weight(self._grid, centre, STILL_REACH * (outline - centre))
        # Output pixels the head's warp can touch: grid cells next to a node it reaches.
        reached = self._grid[self._reach > 0]
        lo = np.maximum(reached.min(0) - GRID_STEP, 0).astype(int) if len(reached) else (0, 0)
        hi = (reached.max(0) + GRID_STEP + 1).astype(int) if len(reached) else (0, 0)
        self._box = (
            (int(lo[0]), int(min(hi[0], self.width))),
            (int(lo[1]), int(min(hi[1], self.height))),
        )
        # The source is padded (below): the warp's maps count from its corner.
        self._pad = GRID_STEP * -(-max(self.width, self.height) // (SOURCE_PAD * GRID_STEP))
        # The person layer's weight rides in the fourth channel, so one remap moves both
        # (and OpenCV remaps four channels faster than three).
        self._layered = person is not None
        self._scene = background
        # Pictures moved by the camera (and the body) alone, kept while they stay where they
        # are (their channels are quantised, so they hold for many frames):
        # (camera and body, which, box) -> picture.
        self._by_camera: dict[tuple[bytes, str, tuple[int, int, int, int]], np.ndarray] = {}
        # The camera's border stays where it is in every frame; what moves is the scene
        # without it (carried in by a pan, a black column showed as a line across the scene).
        self._border = frame_border(background)
        self._clean = self._scene = without_border(background, self._border)
        alpha = np.full((self.height, self.width), 255, np.uint8)
        if person is not None:
            if person.shape != (self.height, self.width):
                raise ValueError(f"expected ({self.height}, {self.width}) person mask")
            weight, painted = _person_layer(person)
            alpha = np.round(255.0 * weight).astype(np.uint8)
            self._scene = _paint_out(self._clean, painted)
        # Padded by the frame's reflection, whose person layer is empty above and beside the
        # frame: what the warp takes from there is scene, never mirrored hair (nor a mirrored
        # shoulder beside a body that shrank). Below the frame a body cut by its bottom edge
        # goes straight on, as bodies do.
        pad = self._pad
        colour = cv2.copyMakeBorder(self._clean, pad, pad, pad, pad, cv2.BORDER_REFLECT_101)
        below = cv2.copyMakeBorder(alpha, 0, pad, 0, 0, cv2.BORDER_REPLICATE)
        layer = cv2.copyMakeBorder(below, pad, 0, pad, pad, cv2.BORDER_CONSTANT, value=0)
        # A person layer's colour is premultiplied by its weight: laid over the scene it is
        # one add of the scene's share (_over), and interpolated it does not bleed what lies
        # outside the person into the person's faded edge. (Without one, all is warped, the
        # reflection beyond the frame too.)
        if self._layered:
            colour = cv2.multiply(colour, cv2.merge([layer] * 3), scale=1 / 255)
        self._source = np.dstack([colour, layer])

    def controls(
        self, outline: np.ndarray, camera: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(now, then): where each control point of the head is in this frame and in the
        snapshot frame (face outline, head ring, still ring).

        ``outline`` (k, 3) is the face outline now, image space ((k, 2): flat); ``camera`` an
        optional (3, 3) homography taking snapshot-frame pixels to this frame's of what does
        not follow the head (the scene, or with :meth:`warp`'s ``body`` the person's body).
        """
        outline3 = _in_space(outline)
        if outline3.shape != self._outline3.shape:
            raise ValueError(f"expected outline of {len(self.outline)} points, got {outline.shape}")
        upper = self._upper
        rotation, scale, shift = similarity_3d(self._outline3[upper], outline3[upper])

        def carried(ring3: np.ndarray, follow: np.ndarray) -> np.ndarray:
            # Where the head's motion takes a ring, by ``follow``; the rest of the way the
            # camera's motion does.
            rigid = (scale * ring3 @ rotation.T + shift)[:, :2]
            still = ring3[:, :2] if camera is None else _apply(camera, ring3[:, :2])
            return still + follow[:, None] * (rigid - still)

        head = carried(self._head3, self._follow)
        ring = carried(self._still3, self._still_follow)
        now = np.concatenate([outline3[:, :2], head, ring])
        then = np.concatenate([self.outline, self._head, self._still])
        return now, then

    def source_map(
        self,
        outline: np.ndarray,
        camera: np.ndarray | None = None,
        box: tuple[int, int, int, int] | None = None,
        origin: int = 0,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Full-size float32 maps (x, y) for ``cv2.remap``: the snapshot pixel each output
        pixel shows; with ``box`` (x0, y0, x1, y1), the maps of that part of the frame.

        The displacement is the camera's (exact, everywhere; or the body's, for the person
        layer) plus the head's: a thin-plate spline through the head's controls, faded to
        nothing just beyond the still ring, so the scene further out is untouched by the
        head. ``origin``: where the snapshot frame's pixel (0, 0) lies in the image remapped
        (0, or the warp's padding).
        """
        camera = None if _is_still(camera) else camera
        x0, y0, x1, y1 = box = box or (0, 0, self.width, self.height)
        both = self._map(outline, camera, box, origin)
        xs, ys = np.meshgrid(
            np.arange(x1 - x0, dtype=np.float32), np.arange(y1 - y0, dtype=np.float32)
        )
        return both[..., 0] + xs, both[..., 1] + ys

    def _map(
        self,
        outline: np.ndarray,
        camera: np.ndarray | None,
        box: tuple[int, int, int, int],
        origin: int,
    ) -> np.ndarray:
        """(y1 - y0, x1 - x0, 2) float32: :meth:`source_map` of ``box`` as one two-channel map
        relative to each pixel of the box (``cv2.WARP_RELATIVE_MAP``: no grid of pixel
        positions to add); a moving ``camera``, or None."""
        now, then = self.controls(outline, camera)
        back = np.linalg.inv(camera) if camera is not None else None
        # Only the nodes around the box, one more on each side: what lies between them is the
        # same as in the whole frame's resize.
        x0, y0, x1, y1 = box
        rows, cols = self._grid_shape
        c0, c1 = max(x0 // GRID_STEP - 1, 0), min(-(-x1 // GRID_STEP) + 1, cols)
        r0, r1 = max(y0 // GRID_STEP - 1, 0), min(-(-y1 // GRID_STEP) + 1, rows)
        nodes = np.s_[r0:r1, c0:c1]
        grid = self._grid.reshape(rows, cols, 2)[nodes].reshape(-1, 2)
        reach = self._reach.reshape(rows, cols)[nodes].ravel()
        shift = np.zeros_like(grid) if back is None else _apply(back, grid) - grid
        # What the head adds to the camera's motion, where its warp reaches.
        reached = reach > 0
        if reached.any():
            residual = then - (now if back is None else _apply(back, now))
            keep = unfolded(now, residual, self._rank)
            spline = ThinPlate(now[keep], residual[keep], SMOOTHING)
            shift[reached] += reach[reached, None] * spline(grid[reached])
        # The box's corner in the image remapped rides on the displacement: interpolation
        # keeps a constant as it is.
        shift += (x0 + origin, y0 + origin)
        # Upsample the displacement, not the position: beyond the outermost nodes resize
        # holds the value, which is right for a displacement that is smooth there.
        coarse = shift.reshape(r1 - r0, c1 - c0, 2).astype(np.float32)
        size = ((c1 - c0) * GRID_STEP, (r1 - r0) * GRID_STEP)
        full = cv2.resize(coarse, size, interpolation=cv2.INTER_LINEAR)
        ox, oy = c0 * GRID_STEP, r0 * GRID_STEP
        return full[y0 - oy : y1 - oy, x0 - ox : x1 - ox]

    def warp(
        self,
        outline: np.ndarray,
        camera: np.ndarray | None = None,
        box: tuple[int, int, int, int] | None = None,
        body: np.ndarray | None = None,
    ) -> np.ndarray:
        """(h, w, 3) uint8: the snapshot frame with the head's surroundings moved along; with
        ``box`` (x0, y0, x1, y1) only that part of it (the sender measures around the face).
        ``body``: an optional (3, 3) homography taking the snapshot frame's person pixels to
        this frame's (the camera's motion included): the person beyond the head's reach
        moves by it, the scene by ``camera`` (without a person layer, all by ``camera``).

        Only the head's reach is warped pixel by pixel; beyond it the snapshot frame is moved
        by the camera alone (copied, when the camera is still), or with a body moving on its
        own, the person by the body over the scene by the camera (kept while both hold), so
        the work grows with the face, not the frame.
        """
        camera = None if _is_still(camera) else camera
        own = (
            self._layered
            and body is not None
            and not np.allclose(body, np.eye(3) if camera is None else camera, rtol=0.0, atol=1e-9)
        )
        person = body if own else None
        bx0, by0, bx1, by1 = box = box or (0, 0, self.width, self.height)
        frame = self._moved("frame", camera, box, person)
        (x0, x1), (y0, y1) = self._box
        x0, x1, y0, y1 = max(x0, bx0), min(x1, bx1), max(y0, by0), min(y1, by1)
        if x1 <= x0 or y1 <= y0:
            return self._with_border(frame.copy(), box)
        reach = (x0, y0, x1, y1)
        # The reach is written below: of a large face's it is all, and nothing need be copied.
        out = np.empty_like(frame) if reach == box else frame.copy()
        # Reflected, not replicated: a frame's dark edge row smeared across a moved-in strip
        # shows as a black band. One two-channel map, no second (the stubs do not know it).
        moved4 = cv2.remap(  # type: ignore[call-overload]
            self._source,
            self._map(outline, camera if person is None else person, reach, self._pad),
            None,
            cv2.INTER_LINEAR | cv2.WARP_RELATIVE_MAP,
            borderMode=cv2.BORDER_REFLECT_101,
        )
        inside = np.s_[y0 - by0 : y1 - by0, x0 - bx0 : x1 - bx0]
        if self._layered:
            _over(moved4, self._moved("scene", camera, reach, person), out[inside])
        else:
            cv2.cvtColor(moved4, cv2.COLOR_BGRA2BGR, dst=out[inside])
        return self._with_border(out, box)

    def _with_border(self, out: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
        """``out``, the part ``box`` of a frame, with the camera's border lines put back
        where the snapshot frame has them."""
        top, bottom, left, right = self._border
        h, w = self.height, self.width
        x0, y0, x1, y1 = box
        for r0, r1, c0, c1 in (
            (0, top, 0, w),
            (h - bottom, h, 0, w),
            (0, h, 0, left),
            (0, h, w - right, w),
        ):
            r0, r1, c0, c1 = max(r0, y0), min(r1, y1), max(c0, x0), min(c1, x1)
            if r1 > r0 and c1 > c0:
                out[r0 - y0 : r1 - y0, c0 - x0 : c1 - x0] = self.background[r0:r1, c0:c1]
        return out

    def _moved(
        self,
        which: str,
        camera: np.ndarray | None,
        box: tuple[int, int, int, int],
        body: np.ndarray | None = None,
    ) -> np.ndarray:
        """The part ``box`` of the snapshot frame (``which`` "frame") or of the scene behind
        the person ("scene") moved by ``camera``; with ``body``, the frame is the person
        layer moved by it over the scene moved by ``camera``: not to be written into."""
        image = self._clean if which == "frame" else self._scene
        if camera is None and body is None:
            return image[box[1] : box[3], box[0] : box[2]]
        motion = b"" if camera is None else camera.tobytes()
        key = (motion + (b"" if body is None else body.tobytes()), which, box)
        if key not in self._by_camera:
            if len(self._by_camera) >= 4 or any(k[0] != key[0] for k in self._by_camera):
                self._by_camera.clear()  # the camera or body moved (or the sender's box did)
            if which == "frame" and body is not None:
                image = self._scene
            x0, y0, x1, y1 = box
            picture = image[y0:y1, x0:x1] if camera is None else _moved(image, camera, box)
            if which == "frame" and body is not None:
                # The padded source (its layer empty above and beside the frame, carried on
                # below it) moved by the body, over the scene moved by the camera.
                pad = self._pad
                unpad = np.array([[1.0, 0.0, -pad], [0.0, 1.0, -pad], [0.0, 0.0, 1.0]])
                picture = _over(_moved(self._source, body @ unpad, box), picture)
            self._by_camera[key] = picture
        return self._by_camera[key]


def _moved(image: np.ndarray, camera: np.ndarray, box: tuple[int, int, int, int]) -> np.ndarray:
    """The part ``box`` (x0, y0, x1, y1) of ``image`` moved by ``camera`` (a (3, 3)
    homography), its border reflected."""
    x0, y0, x1, y1 = box
    to_box = np.array([[1.0, 0.0, -x0], [0.0, 1.0, -y0], [0.0, 0.0, 1.0]]) @ camera
    size, border = (x1 - x0, y1 - y0), cv2.BORDER_REFLECT_101
    # Nearly affine (the sender measures a similarity; its quantised corners add a trace of
    # perspective, under 0.1 px here): the cheaper warp.
    h, w = image.shape[:2]
    tilt = abs(camera[2, 0]) * w + abs(camera[2, 1]) * h
    if tilt < 1e-4 and abs(camera[2, 2] - 1.0) < 1e-9:
        return cv2.warpAffine(image, to_box[:2], size, borderMode=border)
    return cv2.warpPerspective(image, to_box, size, borderMode=border)


def frame_border(image: np.ndarray) -> tuple[int, int, int, int]:
    """(top, bottom, left, right): how many lines at each edge of ``image`` (h, w, 3) are a
    border the camera adds, not the scene (BORDER_MIN and the others): a black bar (BAR_MEDIAN
    and the others), then the lines up to the last one in reach that differs from the next
    line in far more than neighbouring lines further in do. A scene's own strong edge that
    close to the frame's counts too: it is then those few lines that stand still while the
    scene moves."""
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY).astype(np.float32)

    def depth(lines: np.ndarray) -> int:  # (n, length), the outermost line first
        median, upper = np.percentile(lines[: len(lines) // BAR_SHARE], (50, 75), axis=1)
        dark = (median < BAR_MEDIAN) & (upper < BAR_LEVEL)
        bar = int(np.argmin(dark)) if not dark.all() else len(dark)
        lines = lines[bar:]
        reach = max(BORDER_MIN, len(lines) // BORDER_SHARE)
        if len(lines) < 3 * reach:
            return bar
        steps = np.abs(np.diff(lines[: 3 * reach], axis=0)).mean(axis=1)  # line i to i + 1
        typical = float(np.median(steps[reach:]))
        jumps = np.flatnonzero(steps[:reach] > max(BORDER_RATIO * typical, typical + BORDER_STEP))
        return bar + (int(jumps[-1]) + 1 if len(jumps) else 0)

    return depth(grey), depth(grey[::-1]), depth(grey.T), depth(grey.T[::-1])


def without_border(image: np.ndarray, border: tuple[int, int, int, int]) -> np.ndarray:
    """``image`` with its border lines (:func:`frame_border`) replaced by the first line of
    the scene inside them (itself if it has none)."""
    top, bottom, left, right = border
    if not any(border):
        return image
    h, w = image.shape[:2]
    out = image.copy()
    out[:top] = out[top]
    out[h - bottom :] = out[h - bottom - 1]
    out[:, :left] = out[:, left : left + 1]
    out[:, w - right :] = out[:, w - right - 1 : w - right]
    return out


def _over(person: np.ndarray, scene: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(h, w, 3) uint8: the person layer ``person`` (h, w, 4), its colour premultiplied by its
    weight in the fourth channel, over ``scene`` (h, w, 3); written into ``out`` if given."""
    # Integer multiply and add: cv2.blendLinear's float weights cost 3-4 ms at 1280x720, and
    # blending only the pixels of partial weight (indexed) as much (a large face's layer has a
    # long faded edge).
    share = cv2.bitwise_not(person[:, :, 3])  # the scene's: 255 - weight
    behind = cv2.multiply(scene, cv2.merge([share, share, share]), scale=1 / 255)
    return cv2.add(cv2.cvtColor(person, cv2.COLOR_BGRA2BGR), behind, dst=out)


def _person_layer(person: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, painted): the person layer's float32 weight, 1 over the person and a margin
    and fading beyond, and the bool region of the scene to paint out (where alpha is 1)."""
    h, w = person.shape
    margin = max(2, round(PERSON_MARGIN * w))
    hard = (person > PERSON_THRESHOLD).astype(np.uint8)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * margin + 1, 2 * margin + 1))
    painted = cv2.dilate(hard, disc)
    # Grown by a square of the margin, then a box blur of that width: 1 all over ``painted``.
    square = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    grown = cv2.dilate(painted, square).astype(np.float32)
    alpha = cv2.blur(grown, (2 * margin + 1, 2 * margin + 1))
    return np.clip(alpha, 0.0, 1.0), painted.astype(bool)


def _paint_out(image: np.ndarray, region: np.ndarray) -> np.ndarray:
    """``image`` with ``region`` painted in from its surroundings: a smooth blend of them
    (models/fill.py, at a reduced size), which shows only where the person has moved away.
    (Telea's rays drew the shelves beside a head into a star of streaks, seen as soon as the
    head moved.)"""
    if not region.any():
        return image
    h, w = region.shape
    scale = min(1.0, FILL_WIDTH / w)
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    known = cv2.resize((~region).astype(np.uint8), size, interpolation=cv2.INTER_NEAREST)
    filled = fill_invalid(small, cv2.erode(known, np.ones((3, 3), np.uint8)).astype(bool))
    out = image.copy()
    out[region] = cv2.resize(filled, (w, h), interpolation=cv2.INTER_LINEAR)[region]
    return out


def unfolded(points: np.ndarray, shifts: np.ndarray, rank: np.ndarray) -> np.ndarray:
    """(n,) bool: which of the controls ``points`` (n, 2), pixels, with displacements
    ``shifts`` (n, 2) to keep so that no two lie closer than ``UNFOLD`` times the difference
    of their displacements; of two that do, the one of higher ``rank`` (n,) goes.

    A head tilting onto its shoulder carries a control that follows it next to one held
    still: there the displacement changes by more than the distance, and the spline folds the
    snapshot over itself (on Claire's shoulder, a blob of the wall behind)."""
    gap, step = squared_distances(points, points), squared_distances(shifts, shifts)
    clash = np.less(gap, UNFOLD**2 * step)
    keep = np.ones(len(points), bool)
    order = np.argsort(rank)
    for i in order[clash.any(1)[order]]:
        if keep[i]:
            keep[clash[i] & (rank > rank[i])] = False
    return keep


def mouth_line(outline: np.ndarray) -> float:
    """The image row of the mouth's line of a (k, 2+) face outline (MOUTH_LINE)."""
    centre = float(outline[:, 1].mean())
    return centre + MOUTH_LINE * (float(outline[:, 1].max()) - centre)


def carried_by_head(points: np.ndarray, outline: np.ndarray) -> np.ndarray:
    """(m,) bool: which of ``points`` (m, 2) lie where the warp carries the surroundings with the
    head when the snapshot has a person layer (hair, ears, a hat): inside the still ring of
    the face ``outline`` (k, 2+) and above its mouth's line."""
    flat = np.asarray(outline, dtype=np.float64)[:, :2]
    centre = flat.mean(0)
    inside = reach_weight(points, centre, STILL_REACH * (flat - centre)) >= 1.0
    return inside & (points[:, 1] < mouth_line(flat))


def reach_weight(
    points: np.ndarray, centre: np.ndarray, ring: np.ndarray, fade: float = FADE
) -> np.ndarray:
    """(m,) 1 inside the ring (offsets ``ring`` from ``centre``), easing to 0 at ``fade``
    times its radius in each direction."""
    angles = np.arctan2(ring[:, 1], ring[:, 0])
    order = np.argsort(angles)
    radii = np.hypot(ring[:, 0], ring[:, 1])[order]
    d = points - centre
    radius = np.interp(np.arctan2(d[:, 1], d[:, 0]), angles[order], radii, period=2 * np.pi)
    t = np.clip((np.hypot(d[:, 0], d[:, 1]) / radius - 1.0) / (fade - 1.0), 0.0, 1.0)
    return 1.0 - t * t * (3.0 - 2.0 * t)
