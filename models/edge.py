"""The face's edge put where the camera saw it, by a few vectors the sender measures.

The receiver draws the face over the snapshot frame, whose surroundings of the head (hair,
ears, neck) its spline carries along from the face's outline alone (models/surround.py).
Where the two meet the picture is often a pixel or two off: the hair and the neck do not move
exactly as the outline does, and the outline's own vertices are seen edge-on, where the
sender's synthesis cannot see them. That band is a large share of a small face: with the true
frame around the drawn face instead, three of the weakest talking heads scored 0.82-0.86 face
SSIM against 0.76-0.78 (docs/what-we-tried.md, "The face's edge, sent").

So the sender, which can rebuild the receiver's surroundings without drawing, measures the
optical flow from its frame to them at :data:`EDGE_POINTS` points spaced evenly along the
face's outline, and sends the vectors (channel ``edge``). The receiver spreads them by a
thin-plate spline that is zero on the outline scaled by :data:`INNER_REACH` and by
:data:`OUTER_REACH` about its centre, and moves its finished picture by that field
everywhere but the face's inside: its feathered edge and the surroundings move, what the
geometry placed stays.
"""

from __future__ import annotations

import cv2
import numpy as np

from facewire.models.surround import reach_weight
from facewire.models.thin_plate import ThinPlate

#: The channel of the edge's corrections: (x, y) per point, pixels of the call's frame.
EDGE = "edge"
#: Points along the face's outline that carry a correction.
EDGE_POINTS = 16
EDGE_SIZE = 2 * EDGE_POINTS
#: The correction is nothing on the outline scaled by this about its centre (the face's
#: inside, which the geometry places)...
INNER_REACH = 0.7
#: ... and on the outline scaled by this (the background further out stays)...
OUTER_REACH = 2.2
#: ... and it fades to nothing between that ring and this one: the spline is small beyond its
#: outer zeros but not nothing, and the picture must not tear where the field ends.
FADE_REACH = 2.6
#: The spline's regulariser (models/thin_plate.py), pixels^2: the vectors are the flow's, a
#: few tenths of a pixel uncertain, so the field need not pass through them exactly.
SMOOTHING = 2.0
#: The field is evaluated on a grid of this many nodes across the face's width (within
#: MIN/MAX_GRID_STEP pixels apart) and interpolated in between: it changes over the rings'
#: spacing, a third of the face's width.
GRID_ACROSS = 16
MIN_GRID_STEP, MAX_GRID_STEP = 4, 16
#: The most one correction moves the picture, a share of the face's width: the sender sends
#: at most 6%, so a longer one is a broken or hostile value, and must not tear the picture.
MAX_CORRECTION = 0.1
#: The corrections' quantisation step, in units of the face's error budget: the surroundings
#: get twice the face's, as the camera's motion does (0.5 px on a small face).
STEP_PER_BUDGET = 2.0


def edge_step(budget_px: float) -> float:
    """The ``edge`` channel's step, pixels, for a face whose error budget is ``budget_px``."""
    return STEP_PER_BUDGET * budget_px


def outline_ring(outline: np.ndarray, count: int, scale: float = 1.0) -> np.ndarray:
    """(count, 2) points spaced evenly by length along the closed polygon ``outline`` (k, 2),
    scaled by ``scale`` about the polygon's vertex mean."""
    poly = np.asarray(outline, dtype=np.float64)[:, :2]
    closed = np.vstack([poly, poly[:1]])
    length = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))]
    at = np.linspace(0.0, length[-1], count, endpoint=False)
    ring = np.c_[np.interp(at, length, closed[:, 0]), np.interp(at, length, closed[:, 1])]
    centre = poly.mean(0)
    return centre + scale * (ring - centre)


def edge_points(outline: np.ndarray) -> np.ndarray:
    """(EDGE_POINTS, 2) where the edge's corrections apply, from the face's outline (k, 2+)
    in image space: the points both ends agree on."""
    return outline_ring(outline, EDGE_POINTS)


def edge_field(
    outline: np.ndarray, vectors: np.ndarray, box: tuple[int, int, int, int]
) -> np.ndarray:
    """(y1 - y0, x1 - x0, 2) float32: the correction at each pixel of ``box`` (x0, y0, x1,
    y1), pixels.

    ``outline`` (k, 2+) is the face's outline in image space, ``vectors`` (EDGE_POINTS, 2) the
    corrections at its :func:`edge_points`: a pixel at x shows what the uncorrected picture
    has at x + field(x).
    """
    vectors = np.asarray(vectors, dtype=np.float64).reshape(EDGE_POINTS, 2)
    x0, y0, x1, y1 = box
    cols, rows = x1 - x0, y1 - y0
    if not vectors.any():
        return np.zeros((rows, cols, 2), np.float32)
    zero = np.zeros_like(vectors)
    poly = np.asarray(outline, dtype=np.float64)[:, :2]
    centre = poly.mean(0)
    points = edge_points(poly) - centre
    controls = centre + np.vstack([points, INNER_REACH * points, OUTER_REACH * points])
    spline = ThinPlate(controls, np.vstack([vectors, zero, zero]), SMOOTHING)
    # Grid nodes where cv2.resize samples them.
    step = int(np.clip(round(np.ptp(poly[:, 0]) / GRID_ACROSS), MIN_GRID_STEP, MAX_GRID_STEP))
    nx, ny = -(-cols // step), -(-rows // step)
    gx, gy = np.meshgrid(
        x0 + (np.arange(nx) + 0.5) * step - 0.5,
        y0 + (np.arange(ny) + 0.5) * step - 0.5,
    )
    grid = np.c_[gx.ravel(), gy.ravel()]
    field = spline(grid)
    fade = reach_weight(grid, centre, OUTER_REACH * (poly - centre), FADE_REACH / OUTER_REACH)
    field *= fade[:, None]
    coarse = field.reshape(ny, nx, 2).astype(np.float32)
    full = cv2.resize(coarse, (nx * step, ny * step), interpolation=cv2.INTER_LINEAR)
    return full[:rows, :cols]


def move(image: np.ndarray, field: np.ndarray) -> np.ndarray:
    """``image`` (rows, cols, ...) moved by ``field`` (rows, cols, 2) of :func:`edge_field`."""
    # Three channels go through a fourth: OpenCV's remap has vector code for one and four
    # channels and none for three, and a 720x1040 region took 2.7 ms as BGR against 1.6 as
    # BGRA with both conversions, the same values (docs/what-we-tried.md).
    colour = image.ndim == 3 and image.shape[2] == 3
    source = cv2.cvtColor(image, cv2.COLOR_BGR2BGRA) if colour else image
    # One two-channel map (x, y), no second, relative to each pixel: no grid of pixel
    # positions to add (the stubs know neither).
    moved = cv2.remap(  # type: ignore[call-overload]
        source,
        field,
        None,
        cv2.INTER_LINEAR | cv2.WARP_RELATIVE_MAP,
        borderMode=cv2.BORDER_REPLICATE,
    )
    return cv2.cvtColor(moved, cv2.COLOR_BGRA2BGR) if colour else moved


def correct(
    image: np.ndarray,
    face: np.ndarray,
    outline: np.ndarray,
    vectors: np.ndarray,
    band: float,
    depth: tuple[int, int, np.ndarray] | None = None,
) -> np.ndarray:
    """``image`` (h, w, 3), the receiver's finished picture, with its face's edge and
    surroundings moved by the corrections ``vectors`` (EDGE_POINTS, 2) at ``outline``'s
    :func:`edge_points`, in place (a copy of a large frame cost more than the move around a
    small face). The face's inside, where the drawn face (``face``, (h, w) bool) lies deeper
    than ``band`` pixels from its edge, keeps its place. ``depth`` (x, y, distances), the
    distance of each pixel to the face's edge in a box of the picture whose corner is (x,
    y), as the renderer measured it, saves measuring it again."""
    if not np.any(vectors):
        return image
    h, w = image.shape[:2]
    poly = np.asarray(outline, dtype=np.float64)[:, :2]
    limit = MAX_CORRECTION * float(np.ptp(poly[:, 0]))
    length = np.hypot(vectors[:, 0], vectors[:, 1])[:, None]
    vectors = vectors * np.minimum(1.0, limit / np.maximum(length, 1e-9))
    centre = poly.mean(0)
    reach = centre + FADE_REACH * (poly - centre)
    x0, y0 = np.maximum(np.floor(reach.min(0)).astype(int), 0)
    x1, y1 = np.minimum(np.ceil(reach.max(0)).astype(int) + 1, (w, h))
    if x1 <= x0 or y1 <= y0:
        return image
    field = edge_field(poly, vectors, (int(x0), int(y0), int(x1), int(y1)))
    region = image[y0:y1, x0:x1]
    moved = move(region, field)
    # The face's inside keeps its place: where the drawn face lies deeper than the band. The
    # face lies within the outline, well inside the box (all of it that is in the frame).
    # Measured with a border of no face: measured on the face's box cut out, the forehead's
    # and the chin's edge, where they touch the box, counted as deep and were not corrected.
    if depth is None:
        drawn = np.pad(face[y0:y1, x0:x1], 1).view(np.uint8)
        depth = (int(x0), int(y0), cv2.distanceTransform(drawn, cv2.DIST_L2, 3)[1:-1, 1:-1])
    dx, dy, distance = depth[0] - x0, depth[1] - y0, depth[2]
    fx, fy = max(dx, 0), max(dy, 0)
    fw = min(dx + distance.shape[1], x1 - x0) - fx
    fh = min(dy + distance.shape[0], y1 - y0) - fy
    if fw > 0 and fh > 0:
        deep = distance[fy - dy : fy - dy + fh, fx - dx : fx - dx + fw] > band
        keep = np.s_[fy : fy + fh, fx : fx + fw]
        cv2.copyTo(region[keep], deep.view(np.uint8), moved[keep])
    region[...] = moved
    return image
