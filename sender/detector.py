"""Face detection with MediaPipe's BlazeFace short-range model (run by models/network.py).

The detector only chooses where the landmark model looks: it runs on the first frame and
after the tracker loses the face. Coordinates are OpenCV pixel coordinates of the input
frame (pixel centres at integers, x right, y down).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import cv2
import numpy as np

from facewire.models.network import Network, rgb_input

logger = logging.getLogger(__name__)

INPUT_SIZE = 128
# Graph outputs: box + keypoint regressions (1, 896, 16), score logits (1, 896, 1).
OUTPUT_LAYERS = ["regressors", "classificators"]
# SSD anchor layout of the short-range model: one feature map per stride, and layers
# sharing a stride are merged, so stride 8 has 2 anchors per cell and stride 16 has 6.
_ANCHOR_LAYOUT = ((8, 2), (16, 6))
KEYPOINT_NAMES = ("right_eye", "left_eye", "nose_tip", "mouth", "right_ear", "left_ear")
"""Keypoint order; "right" is the face's right, i.e. image left for a frontal face."""


def model_path(name: str) -> Path:
    """Path of a file shipped in sender/data."""
    return Path(str(resources.files("facewire.sender") / "data" / name))


def ssd_anchors(size: int = INPUT_SIZE) -> np.ndarray:
    """(n, 2) anchor centres of a ``size``-pixel input (896 at 128), normalised [0, 1] input
    coordinates (x, y). MediaPipe's palm detector has the same layout at 192."""
    out = []
    for stride, per_cell in _ANCHOR_LAYOUT:
        fm = size // stride
        c = (np.arange(fm) + 0.5) / fm
        xx, yy = np.meshgrid(c, c)
        cells = np.stack([xx.ravel(), yy.ravel()], axis=1)
        out.append(np.repeat(cells, per_cell, axis=0))
    return np.concatenate(out)


@dataclass(frozen=True)
class Detection:
    """One detected face.

    box : (4,) float64, (x0, y0, x1, y1) image pixels
    keypoints : (6, 2) float64, image pixels, in ``KEYPOINT_NAMES`` order
    score : float, 0..1
    """

    box: np.ndarray
    keypoints: np.ndarray
    score: float

    @property
    def centre(self) -> np.ndarray:
        return np.array([(self.box[0] + self.box[2]) / 2, (self.box[1] + self.box[3]) / 2])

    @property
    def size(self) -> float:
        """Larger side of the box, pixels."""
        return float(max(self.box[2] - self.box[0], self.box[3] - self.box[1]))


def decode(
    regressors: np.ndarray, logits: np.ndarray, anchors: np.ndarray, size: int = INPUT_SIZE
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw SSD outputs of a ``size``-pixel input -> boxes, keypoints and scores in normalised
    input coordinates.

    regressors : (n, 4 + 2k) float; logits : (n,) float; anchors : (n, 2).
    Returns boxes (n, 4) (x0, y0, x1, y1), keypoints (n, k, 2), scores (n,).
    """
    r = regressors.astype(np.float64) / size
    centre = r[:, :2] + anchors
    half = r[:, 2:4] / 2
    boxes = np.concatenate([centre - half, centre + half], axis=1)
    kps = r[:, 4:].reshape(len(r), -1, 2) + anchors[:, None, :]
    # Clip like MediaPipe so exp() cannot overflow on garbage input.
    scores = 1.0 / (1.0 + np.exp(-np.clip(logits.astype(np.float64), -100, 100)))
    return boxes, kps, scores


def box_iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Intersection over union of ``box`` (4,) with each of ``boxes`` (n, 4), (x0, y0, x1, y1)."""
    x0 = np.maximum(box[0], boxes[:, 0])
    y0 = np.maximum(box[1], boxes[:, 1])
    x1 = np.minimum(box[2], boxes[:, 2])
    y1 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = (box[2] - box[0]) * (box[3] - box[1])
    areas = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])
    return inter / np.maximum(area + areas - inter, 1e-12)


def weighted_nms(
    boxes: np.ndarray, kps: np.ndarray, scores: np.ndarray, iou_threshold: float
) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """MediaPipe-style blending NMS: each kept box is the score-weighted mean of its cluster.

    Averaging the overlapping anchors steadies the keypoints that set the crop's roll.
    Returns (box (4,), keypoints (k, 2), score) best first.
    """
    order = np.argsort(-scores)
    boxes, kps, scores = boxes[order], kps[order], scores[order]
    alive = np.ones(len(scores), dtype=bool)
    out = []
    for i in range(len(scores)):
        if not alive[i]:
            continue
        members = alive & (box_iou(boxes[i], boxes) > iou_threshold)
        members[i] = True
        alive &= ~members
        w = scores[members] / scores[members].sum()
        box = (boxes[members] * w[:, None]).sum(axis=0)
        kp = (kps[members] * w[:, None, None]).sum(axis=0)
        out.append((box, kp, float(scores[i])))
    return out


def square_input(frame_bgr: np.ndarray, size: int) -> tuple[np.ndarray, int, np.ndarray]:
    """``frame_bgr`` padded to a centred square (so a network sees it undistorted) and
    resized to ``size``; the square's side and the frame's (x, y) offset in it, pixels."""
    h, w = frame_bgr.shape[:2]
    side = max(h, w)
    top, left = (side - h) // 2, (side - w) // 2
    square = cv2.copyMakeBorder(
        frame_bgr, top, side - h - top, left, side - w - left, cv2.BORDER_CONSTANT, value=0
    )
    small = cv2.resize(square, (size, size), interpolation=cv2.INTER_AREA)
    return small, side, np.array([left, top], dtype=np.float64)


class FaceDetector:
    """BlazeFace short-range: finds faces that fill roughly 20-100 % of a square frame.

    Input normalisation is RGB scaled to [-1, 1] (checked on the astronaut fixture: the
    face scores 0.96 with [-1, 1] against 0.94 with [0, 1]).
    """

    def __init__(
        self,
        path: str | Path | None = None,
        min_score: float = 0.5,
        iou_threshold: float = 0.3,
    ) -> None:
        self.path = (
            Path(path) if path is not None else model_path("face_detection_short_range.tflite")
        )
        self.net = Network(self.path)
        self.min_score = min_score
        self.iou_threshold = iou_threshold
        self.anchors = ssd_anchors()

    def detect(self, frame_bgr: np.ndarray) -> list[Detection]:
        """Faces in ``frame_bgr`` ((h, w, 3) uint8 BGR, any size), best first."""
        if frame_bgr.ndim != 3 or frame_bgr.shape[2] != 3 or frame_bgr.dtype != np.uint8:
            raise ValueError(
                f"expected (h, w, 3) uint8 BGR frame, got {frame_bgr.shape} {frame_bgr.dtype}"
            )
        small, side, offset = square_input(frame_bgr, INPUT_SIZE)
        out = self.net.run(rgb_input(small, 1 / 127.5, -1.0))
        regressors, logits = (out[name] for name in OUTPUT_LAYERS)
        boxes, kps, scores = decode(regressors[0], logits.reshape(-1), self.anchors)
        keep = scores >= self.min_score
        if not keep.any():
            return []
        # Normalised coordinates are continuous ([0, 1] spans the whole square); shift by
        # half a pixel to OpenCV's pixel-centre convention.
        to_px = np.float64(side)
        dets = []
        for box, kp, score in weighted_nms(
            boxes[keep], kps[keep], scores[keep], self.iou_threshold
        ):
            b = box * to_px - 0.5 - np.tile(offset, 2)
            k = kp * to_px - 0.5 - offset
            dets.append(Detection(b, k, score))
        logger.debug("detected %d faces, best score %.3f", len(dets), dets[0].score)
        return dets


# Faces within this fraction of the largest one's size count as "as large".
SIZE_TIE = 0.85


def largest_first(
    detections: list[Detection], width: int | None = None, height: int | None = None
) -> list[Detection]:
    """Detections in the order the tracker tries them: the largest face first.

    With several people in view the tracker takes the largest face, i.e. usually the
    person nearest the camera, and keeps following it once it has it. Faces at least
    ``SIZE_TIE`` as large as the largest count as equally large and go nearest the frame's
    centre first (when the frame size is given), so a box a few pixels bigger does not
    decide between two similar faces.
    """
    if not detections:
        return []
    by_size = sorted(detections, key=lambda d: (-d.size, -d.score))
    biggest = by_size[0].size
    top = [d for d in by_size if d.size >= SIZE_TIE * biggest]
    rest = [d for d in by_size if d.size < SIZE_TIE * biggest]
    if width is not None and height is not None:
        centre = np.array([(width - 1) / 2, (height - 1) / 2])
        top.sort(key=lambda d: float(np.linalg.norm(d.centre - centre)))
    return top + rest


def merge_overlapping(detections: list[Detection], iou_threshold: float) -> list[Detection]:
    """Keep the best-scoring detection of each group of overlapping boxes (same face seen by
    several overlapping tiles), best score first."""
    kept: list[Detection] = []
    for det in sorted(detections, key=lambda d: -d.score):
        if not kept or (box_iou(det.box, np.array([k.box for k in kept])) <= iou_threshold).all():
            kept.append(det)
    return kept


# Measured on the astronaut fixture scaled into 128-256 px squares: BlazeFace short-range finds
# every face whose landmark width is at least 14 % of the square's side and none below 10 %.
# Tiles are sized so a face of ``min_face`` px is 19 % of a tile: safely inside the range.
TILE_FACE_FRACTION = 0.19
# A face up to this fraction of a tile's side lies wholly inside some tile at half-tile
# stride (its box, about 1.1 times its landmark width, is at most half a tile).
TILE_FACE_MAX = 0.45
# A tile's candidates must score this much: the many tiles of a large frame would otherwise
# let through the detector's false positives (on textures they scored up to 0.70; faces that
# fill 14 % or more of a tile scored 0.81 and up).
TILE_MIN_SCORE = 0.75
# Faces at least this fraction of the frame's larger side are left to the whole-frame pass.
WHOLE_FRAME_FACE_FRACTION = 0.16


def tile_grid(width: int, height: int, min_face: float = 48.0) -> list[tuple[int, int, int]]:
    """Square tiles (x0, y0, side) that a second look at small faces searches, coarse first.

    The finest level's tiles have side ``min_face / TILE_FACE_FRACTION``; each further
    level doubles the side, until the faces a level holds reach the whole-frame pass's
    range. Tiles overlap by half a tile, the last one flush with the frame's edge, so any
    face from ``min_face`` px up lies wholly inside a tile it fills 14-45 % of. Tiles
    larger than the frame are clipped to it. Empty when the whole-frame pass already finds
    faces of ``min_face`` px.
    """
    if width < 1 or height < 1:
        raise ValueError(f"expected a positive frame size, got {width}x{height}")
    if not min_face > 0:
        raise ValueError(f"expected positive min_face, got {min_face}")
    big = max(width, height)
    whole_frame_min = WHOLE_FRAME_FACE_FRACTION * big
    if min_face >= whole_frame_min:
        return []
    levels = [min_face / TILE_FACE_FRACTION]
    while TILE_FACE_MAX * levels[-1] < whole_frame_min and 2 * levels[-1] < big:
        levels.append(2 * levels[-1])
    tiles: list[tuple[int, int, int]] = []
    for side in reversed(levels):
        s = int(round(side))
        tiles.extend((x, y, s) for y in _starts(height, s) for x in _starts(width, s))
    return tiles


def _starts(length: int, side: int) -> list[int]:
    """Tile origins along one axis: half-tile stride, the last tile flush with the edge."""
    if side >= length:
        return [0]
    stride = max(side // 2, 1)
    starts = list(range(0, length - side, stride))
    starts.append(length - side)
    return starts


class TileSearch:
    """A second look for faces too small for the whole-frame pass, a few tiles per call.

    ``scan`` runs the detector on the next ``budget`` tiles of the frame (all of them when
    None) and returns what it found there in frame coordinates, merged across tiles; the
    cursor wraps round, so a video is searched over several frames at a bounded cost per
    frame. A change of frame size restarts the search.
    """

    def __init__(
        self, detector: FaceDetector, min_face: float = 48.0, min_score: float = TILE_MIN_SCORE
    ) -> None:
        self.detector = detector
        self.min_face = min_face
        self.min_score = min_score
        self._size: tuple[int, int] | None = None
        self._tiles: list[tuple[int, int, int]] = []
        self._cursor = 0

    def tiles(self, width: int, height: int) -> list[tuple[int, int, int]]:
        if self._size != (width, height):
            self._size = (width, height)
            self._tiles = tile_grid(width, height, self.min_face)
            self._cursor = 0
        return self._tiles

    def restart(self) -> None:
        """The next scan starts with the coarsest tiles."""
        self._cursor = 0

    def scan(self, frame_bgr: np.ndarray, budget: int | None = None) -> list[Detection]:
        h, w = frame_bgr.shape[:2]
        tiles = self.tiles(w, h)
        if not tiles:
            return []
        n = len(tiles) if budget is None else min(max(budget, 1), len(tiles))
        found = []
        for _ in range(n):
            x0, y0, side = tiles[self._cursor]
            self._cursor = (self._cursor + 1) % len(tiles)
            offset = np.array([x0, y0], dtype=np.float64)
            for d in self.detector.detect(frame_bgr[y0 : y0 + side, x0 : x0 + side]):
                if d.score < self.min_score:
                    continue
                found.append(Detection(d.box + np.tile(offset, 2), d.keypoints + offset, d.score))
        merged = merge_overlapping(found, self.detector.iou_threshold)
        if merged:
            logger.debug("tile search: %d faces in %d tiles", len(merged), n)
        return merged
