"""Sticker marker colours: read from the first frames, then found by colour every frame.

Colours are compared by hue and saturation (OpenCV's HSV: hue 0..180, saturation and value
0..255). Both are ratios of the pixel's channels, so a brighter or dimmer light, or a face
turning into shadow, leaves them where they were; only a floor on the value (a fraction of
the markers' own) keeps the noisy hue of near-black pixels out.

Calibration needs to know roughly where each marker is (the landmark tracker's vertex under
it, a few pixels off): within a small window it takes the pixels whose chromaticity (each
channel over their sum, again free of brightness) stands furthest from the skin around the
window, and the blob of them nearest the expected place is the marker. Markers of similar
hue are pooled into one colour class, so any colours work, one per role as in the bundled
clip (seed 002's red pose points and yellow deformation points would do as well) or all
alike (identities then come from the layout alone).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

logger = logging.getLogger(__name__)

# A marker's chromaticity must differ from the skin around it by this much (sum-normalised
# BGR, 0..~1.4): a saturated sticker is 0.3-0.6 from skin, skin's own shading under 0.05.
MIN_CHROMA_CONTRAST = 0.12
# Markers this close in hue (OpenCV units, 0..180) share a colour class.
SAME_HUE = 14.0
# Below this saturation (0..255) hue means little: such a marker cannot be told by colour.
MIN_MARKER_SATURATION = 90.0
# A class accepts hues within max(MIN_HUE_TOLERANCE, HUE_SPREAD x its markers' spread).
MIN_HUE_TOLERANCE = 7.0
HUE_SPREAD = 2.0
# ... and saturation above this fraction of its markers' median, value above this fraction.
SATURATION_FRACTION = 0.5
VALUE_FRACTION = 0.3
# Blobs smaller than this fraction of a calibrated marker's area are noise.
MIN_AREA_FRACTION = 0.2


@dataclass(frozen=True)
class ColourClass:
    """Pixels with hue within ``hue_tolerance`` of ``hue`` (OpenCV units, 0..180, circular),
    saturation at least ``min_saturation`` and value at least ``min_value`` (0..255)."""

    hue: float
    hue_tolerance: float
    min_saturation: float
    min_value: float
    saturation: float  # the markers' median saturation, for centroid weights

    def label(self) -> str:
        return (
            f"hue {self.hue:.0f}+-{self.hue_tolerance:.0f}, saturation >= {self.min_saturation:.0f}"
        )


@dataclass(frozen=True)
class Blobs:
    """Connected blobs of one colour class in a frame.

    centroids : (b, 2) image px, weighted by how saturated each pixel is, taken within a
        marker's reach of the blob's peak (a shadow or lip run into the blob is left out)
    areas : (b,) pixels; boxes : (b, 4) x0, y0, x1, y1 (exclusive) image px
    """

    centroids: np.ndarray
    areas: np.ndarray
    boxes: np.ndarray
    _xy: np.ndarray  # (p, 2) image px of the class's pixels in blobs
    _weight: np.ndarray  # (p,) their centroid weights
    _blob: np.ndarray  # (p,) the blob each belongs to

    def __len__(self) -> int:
        return len(self.areas)

    def pixels(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(p, 2) image px of blob i's pixels and (p,) their weights."""
        sel = self._blob == i
        return self._xy[sel], self._weight[sel]


def hue_distance(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray:
    """Circular distance between OpenCV hues (0..180)."""
    d = np.abs(np.asarray(a, dtype=np.float64) - b) % 180.0
    return np.minimum(d, 180.0 - d)


def circular_mean_hue(hues: np.ndarray) -> float:
    ang = np.asarray(hues, dtype=np.float64) * (2 * np.pi / 180.0)
    mean = np.arctan2(np.sin(ang).mean(), np.cos(ang).mean())
    return float((mean * 180.0 / (2 * np.pi)) % 180.0)


def chromaticity(bgr: np.ndarray) -> np.ndarray:
    """(..., 3) each channel over the sum of the three: the colour without its brightness."""
    f = bgr.astype(np.float32)
    return f / np.maximum(f.sum(axis=-1, keepdims=True), 1.0)


@dataclass(frozen=True)
class MarkerSample:
    """One marker as calibration found it: centroid (2,) px, area px, median hue,
    saturation and value of its most distinct pixels."""

    centroid: np.ndarray
    area: float
    hue: float
    saturation: float
    value: float


def sample_marker(image: np.ndarray, expected: np.ndarray, radius: float) -> MarkerSample | None:
    """The marker near ``expected`` (2,) px in ``image`` (BGR uint8), looked for within
    ``radius`` px; None when nothing there stands out from the skin around it.

    The marker is the most distinct spot within reach (chromaticity furthest from the skin
    round the window) and the pixels joined to it that are at least half as distinct: a
    sticker is distinct all over, hair or a lip beside it much less so.
    """
    h, w = image.shape[:2]
    r = max(3, int(np.ceil(radius)))
    ring = 2 * r
    cx, cy = int(round(expected[0])), int(round(expected[1]))
    x0, y0 = max(cx - ring, 0), max(cy - ring, 0)
    x1, y1 = min(cx + ring + 1, w), min(cy + ring + 1, h)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return None
    patch = image[y0:y1, x0:x1]
    chroma = chromaticity(patch)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    dist = np.hypot(xx - expected[0], yy - expected[1])
    outer = dist > r
    if outer.sum() < 8:
        return None
    skin = np.median(chroma[outer], axis=0)
    contrast = np.linalg.norm(chroma - skin, axis=-1)
    # Dark pixels have unreliable chromaticity (hair, shadows, nostrils).
    contrast[patch.astype(np.int32).sum(axis=-1) <= 90] = 0.0
    reach = np.where(dist <= r, contrast, 0.0)
    peak = float(reach.max())
    if peak <= MIN_CHROMA_CONTRAST:
        return None
    py, px = np.unravel_index(int(np.argmax(reach)), reach.shape)
    distinct = (contrast >= max(MIN_CHROMA_CONTRAST, 0.5 * peak)).astype(np.uint8)
    _, labels = cv2.connectedComponents(distinct, connectivity=8)
    member = labels == labels[py, px]
    if member.sum() < 3:
        return None
    wts = contrast[member]
    centroid = np.array(
        [(xx[member] * wts).sum() / wts.sum(), (yy[member] * wts).sum() / wts.sum()]
    )
    hsv = cv2.cvtColor(patch, cv2.COLOR_BGR2HSV)[member]
    # The most distinct half: the sticker's own colour, not its blended rim.
    core = wts >= np.median(wts)
    return MarkerSample(
        centroid,
        float(member.sum()),
        circular_mean_hue(hsv[core, 0]),
        float(np.median(hsv[core, 1])),
        float(np.median(hsv[core, 2])),
    )


def colour_classes(samples: list[MarkerSample]) -> tuple[list[ColourClass], np.ndarray]:
    """Pool markers of similar hue into classes: (classes, (k,) class of each sample)."""
    if not samples:
        return [], np.zeros(0, dtype=np.int64)
    hues = np.array([s.hue for s in samples])
    # Single linkage on the circle: walk the sorted hues and cut at gaps wider than SAME_HUE
    # (and across the widest gap, where the circle is opened).
    order = np.argsort(hues)
    sorted_h = hues[order]
    gaps = np.diff(np.concatenate([sorted_h, [sorted_h[0] + 180.0]]))
    start = (int(np.argmax(gaps)) + 1) % len(order)
    walk = np.roll(order, -start)
    group = np.zeros(len(samples), dtype=np.int64)
    g = 0
    for a, b in zip(walk[:-1], walk[1:], strict=True):
        group[b] = g if hue_distance(hues[a], hues[b]) <= SAME_HUE else (g := g + 1)
    group[walk[0]] = 0
    classes = []
    for c in range(g + 1):
        members = [s for s, gi in zip(samples, group, strict=True) if gi == c]
        mh = np.array([s.hue for s in members])
        centre = circular_mean_hue(mh)
        spread = float(hue_distance(mh, centre).max())
        sat = float(np.median([s.saturation for s in members]))
        val = float(np.median([s.value for s in members]))
        classes.append(
            ColourClass(
                hue=centre,
                hue_tolerance=max(MIN_HUE_TOLERANCE, HUE_SPREAD * spread),
                min_saturation=SATURATION_FRACTION * sat,
                min_value=VALUE_FRACTION * val,
                saturation=sat,
            )
        )
    return classes, group


def class_mask(hsv: np.ndarray, cls: ColourClass) -> np.ndarray:
    """(h, w) uint8 255 where a pixel of ``hsv`` belongs to ``cls``."""
    lo_s, lo_v = int(np.ceil(cls.min_saturation)), int(np.ceil(cls.min_value))
    h0, h1 = cls.hue - cls.hue_tolerance, cls.hue + cls.hue_tolerance
    ranges = []
    if h0 < 0:
        ranges += [(0.0, h1), (180.0 + h0, 180.0)]
    elif h1 >= 180:
        ranges += [(h0, 180.0), (0.0, h1 - 180.0)]
    else:
        ranges.append((h0, h1))
    mask = None
    for a, b in ranges:
        m = cv2.inRange(
            hsv,
            np.array([int(np.ceil(a)), lo_s, lo_v], dtype=np.uint8),
            np.array([min(int(np.floor(b)), 179), 255, 255], dtype=np.uint8),
        )
        mask = m if mask is None else cv2.bitwise_or(mask, m)
    assert mask is not None
    return mask


def find_blobs(
    hsv: np.ndarray,
    classes: list[ColourClass],
    origin: tuple[int, int],
    min_area: float,
    reach: float,
) -> list[Blobs]:
    """Blobs of each class in ``hsv`` (a region of the frame whose top-left pixel is
    ``origin``), one :class:`Blobs` per class. ``reach`` (px) is how far from a blob's
    centre its centroid looks (about a marker's radius and a half)."""
    masks = [class_mask(hsv, c) for c in classes]
    combined = masks[0]
    for m in masks[1:]:
        combined = cv2.bitwise_or(combined, m)
    # One labelling for all classes (it is most of the cost); a component's pixels of each
    # class are that class's blob.
    _, labels = cv2.connectedComponents(combined, connectivity=8)
    nz = cv2.findNonZero(combined)
    out = []
    sat_all = hsv[..., 1]
    for mask, cls in zip(masks, classes, strict=True):
        if nz is None:
            out.append(_no_blobs())
            continue
        pts = nz.reshape(-1, 2)
        pts = pts[mask[pts[:, 1], pts[:, 0]] > 0]
        out.append(_blobs_of(pts, labels, sat_all, cls, origin, min_area, reach))
    return out


def _no_blobs() -> Blobs:
    return Blobs(
        np.zeros((0, 2)),
        np.zeros(0),
        np.zeros((0, 4), dtype=np.int64),
        np.zeros((0, 2)),
        np.zeros(0),
        np.zeros(0, dtype=np.int64),
    )


def _blobs_of(
    pts: np.ndarray,
    labels: np.ndarray,
    sat: np.ndarray,
    cls: ColourClass,
    origin: tuple[int, int],
    min_area: float,
    reach: float,
) -> Blobs:
    if not len(pts):
        return _no_blobs()
    lab = labels[pts[:, 1], pts[:, 0]]
    uniq, blob, area = np.unique(lab, return_inverse=True, return_counts=True)
    keep = area >= min_area
    if not keep.any():
        return _no_blobs()
    renum = np.full(len(uniq), -1, dtype=np.int64)
    renum[keep] = np.arange(int(keep.sum()))
    blob = renum[blob]
    sel = blob >= 0
    pts, blob = pts[sel], blob[sel]
    n = int(keep.sum())
    # Centroid weights: how far above the class's saturation floor a pixel is, so a rim
    # blended with skin counts for little.
    span = max(cls.saturation - cls.min_saturation, 1.0)
    s = sat[pts[:, 1], pts[:, 0]].astype(np.float64)
    w = np.clip((s - cls.min_saturation) / span, 0.05, 1.0)
    xy = pts.astype(np.float64) + np.array(origin, dtype=np.float64)
    sw = np.bincount(blob, w, n)
    cent: np.ndarray = (
        np.column_stack([np.bincount(blob, w * xy[:, 0], n), np.bincount(blob, w * xy[:, 1], n)])
        / sw[:, None]
    )
    # Mean shift within ``reach``: whatever ran into the marker's blob is left out.
    for _ in range(2):
        near = np.linalg.norm(xy - cent[blob], axis=1) <= reach
        wn = np.where(near, w, 0.0)
        swn = np.bincount(blob, wn, n)
        ok = swn > 0
        c2 = np.column_stack(
            [np.bincount(blob, wn * xy[:, 0], n), np.bincount(blob, wn * xy[:, 1], n)]
        )
        cent[ok] = c2[ok] / swn[ok, None]
    lo = np.full((n, 2), np.inf)
    hi = np.full((n, 2), -np.inf)
    np.minimum.at(lo, blob, xy)
    np.maximum.at(hi, blob, xy)
    boxes = np.column_stack([lo, hi + 1]).astype(np.int64)
    return Blobs(cent, area[keep].astype(np.float64), boxes, xy, w, blob)


def split_blob(pixels: np.ndarray, weights: np.ndarray, seeds: np.ndarray) -> np.ndarray:
    """Centroids (s, 2) of a blob's pixels (p, 2) split among ``seeds`` (s, 2) by weighted
    k-means started at the seeds (two markers run into one blob).

    Two seeds start from the blob's own long axis instead (a seed far off, a marker that was
    hidden, would otherwise take no pixels), and the halves go to the seeds in their order
    along that axis.
    """
    centres = np.asarray(seeds, dtype=np.float64).copy()
    if len(centres) == 2 and weights.sum() > 0:
        mean = (pixels * weights[:, None]).sum(axis=0) / weights.sum()
        rel = pixels - mean
        cov = (rel * weights[:, None]).T @ rel / weights.sum()
        axis = np.linalg.eigh(cov)[1][:, -1]
        spread = float(np.sqrt(max(axis @ cov @ axis, 1e-6)))
        ends = mean + np.outer([-spread, spread], axis)
        order = np.argsort((centres - mean) @ axis)
        centres = ends[np.argsort(order)]
    for _ in range(10):
        d = np.linalg.norm(pixels[:, None] - centres[None], axis=2)
        owner = d.argmin(axis=1)
        moved = 0.0
        for j in range(len(centres)):
            sel = owner == j
            if weights[sel].sum() <= 0:
                continue
            c = (pixels[sel] * weights[sel, None]).sum(axis=0) / weights[sel].sum()
            moved = max(moved, float(np.linalg.norm(c - centres[j])))
            centres[j] = c
        if moved < 1e-3:
            break
    return centres
