"""Picture quality of a call against its input: PSNR and SSIM of luma, by region.

Frame i of the output is scored against frame i of the input: frames are aligned by index,
never by container timestamps. An output frame that is missing (dropped, or the output ends
early) counts as the previous output frame held on screen.

Three regions, each made from the INPUT frame's own 468 landmarks (``facewire.sender.landmarks``):

- ``face``: the convex hull of the landmarks' (x, y);
- ``head``: the face hull widened to take in hair, ears and chin (see :func:`head_polygon`);
- ``frame``: the whole image.

SSIM is Wang et al. (2004): luma, an 11x11 Gaussian window of sigma 1.5 (truncated at 3.5
sigma, weights summing to one), K1 = 0.01, K2 = 0.03, L = 255, population statistics,
image edges reflected (the same map as scikit-image's ``structural_similarity`` with
``gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=255``). The
SSIM of a region is the mean of the SSIM map over the region's pixels; over the frame that
includes the border pixels that scikit-image's mean leaves out. PSNR of a region is
``10 log10(255^2 / MSE)`` of luma over its pixels: infinite for identical pixels, capped
at :data:`PSNR_CAP_DB` when frames are averaged.

The metric functions are pure functions over numpy arrays; :func:`score_videos` reads two
files and runs the landmark tracker over the input.
"""

from __future__ import annotations

import itertools
import logging
import math
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from facewire.receiver.recorder import crop_to, padded_size

if TYPE_CHECKING:
    from facewire.sender.landmarks import LandmarkTracker

logger = logging.getLogger(__name__)

REGIONS = ("face", "head", "frame")
#: A frame's PSNR is capped at this when frames are averaged (identical frames are infinite).
PSNR_CAP_DB = 100.0

# Wang et al. 2004, section III-C.
SSIM_SIGMA = 1.5
SSIM_RADIUS = int(3.5 * SSIM_SIGMA + 0.5)  # 5: an 11x11 window, as scipy.ndimage truncates it
SSIM_K1, SSIM_K2 = 0.01, 0.03
PEAK = 255.0

# The head region, in the face's upright frame (eye line horizontal, y down), about the
# centre of the face hull's bounding box: widths x HEAD_WIDTH (the ears sit beside the mesh's
# outline), heights above the centre x HEAD_UP (the mesh stops at the hairline; the skull and
# hair reach about another 0.3 face heights), below x HEAD_DOWN (a margin under the chin).
HEAD_WIDTH = 1.3
HEAD_UP = 1.6
HEAD_DOWN = 1.15
# MediaPipe indices of the face's right and left outer eye corners: the face's roll.
_RIGHT_EYE_OUTER = 33
_LEFT_EYE_OUTER = 263
N_LANDMARKS = 468


def luma(image: np.ndarray) -> np.ndarray:
    """(h, w) float64 luma (BT.601: 0.299 R + 0.587 G + 0.114 B) of a BGR or grey image.

    image : (h, w, 3) BGR or (h, w) grey, uint8 or float in 0..255
    """
    a = np.asarray(image)
    if a.ndim == 2:
        return a.astype(np.float64)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected an (h, w, 3) BGR or (h, w) grey image, got {a.shape}")
    b, g, r = (a[..., i].astype(np.float64) for i in range(3))
    return 0.299 * r + 0.587 * g + 0.114 * b


def _check_pair(reference: np.ndarray, test: np.ndarray) -> None:
    if reference.shape[:2] != test.shape[:2]:
        raise ValueError(
            f"images differ in size: {_size(test)} against a reference of {_size(reference)}"
        )


def _size(a: np.ndarray) -> str:
    return f"{a.shape[1]}x{a.shape[0]}"


def _blur(x: np.ndarray) -> np.ndarray:
    k = 2 * SSIM_RADIUS + 1
    return np.asarray(
        cv2.GaussianBlur(x, (k, k), SSIM_SIGMA, sigmaY=SSIM_SIGMA, borderType=cv2.BORDER_REFLECT)
    )


def ssim_map(reference: np.ndarray, test: np.ndarray) -> np.ndarray:
    """(h, w) float64 SSIM map of the luma of two images of one size (see the module doc)."""
    _check_pair(reference, test)
    x, y = luma(reference), luma(test)
    if min(x.shape) < 2 * SSIM_RADIUS + 1:
        raise ValueError(f"images must be at least 11x11 for SSIM, got {_size(x)}")
    mx, my = _blur(x), _blur(y)
    vx = _blur(x * x) - mx * mx
    vy = _blur(y * y) - my * my
    vxy = _blur(x * y) - mx * my
    c1, c2 = (SSIM_K1 * PEAK) ** 2, (SSIM_K2 * PEAK) ** 2
    num = (2 * mx * my + c1) * (2 * vxy + c2)
    den = (mx * mx + my * my + c1) * (vx + vy + c2)
    return np.asarray(num / den)


def _mask_or_all(mask: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray | None:
    if mask is None:
        return None
    m = np.asarray(mask, dtype=bool)
    if m.shape != shape[:2]:
        raise ValueError(f"mask is {m.shape[1]}x{m.shape[0]}, images are {shape[1]}x{shape[0]}")
    return m


def masked_mean(values: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean of ``values`` over ``mask`` ((h, w) bool; None: everywhere); nan for an empty mask."""
    m = _mask_or_all(mask, values.shape)
    if m is None:
        return float(values.mean())
    if not m.any():
        return math.nan
    return float(values[m].mean())


def ssim(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None) -> float:
    """SSIM of luma over ``mask`` ((h, w) bool; None: the whole frame)."""
    return masked_mean(ssim_map(reference, test), mask)


def psnr(reference: np.ndarray, test: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR of luma in dB over ``mask`` ((h, w) bool; None: the whole frame).

    ``inf`` when the pixels are identical, nan for an empty mask.
    """
    _check_pair(reference, test)
    err = (luma(reference) - luma(test)) ** 2
    return _decibels(masked_mean(err, mask))


def _decibels(mse: float) -> float:
    if math.isnan(mse):
        return math.nan
    if mse == 0:
        return math.inf
    return 10 * math.log10(PEAK**2 / mse)


def _upright(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Landmarks in the face's upright frame, and the rotation that maps them back."""
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    d = xy[_LEFT_EYE_OUTER] - xy[_RIGHT_EYE_OUTER]
    angle = math.atan2(d[1], d[0])
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])  # upright -> image
    return xy @ rot, rot  # rows are rot.T @ p


def _check_points(points: np.ndarray) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[0] != N_LANDMARKS or p.shape[1] < 2:
        raise ValueError(f"expected ({N_LANDMARKS}, 2 or 3) landmarks, got {p.shape}")
    return p


def face_polygon(points: np.ndarray) -> np.ndarray:
    """(k, 2) float64 convex hull (image pixels) of 468 landmarks ((468, 2+) image pixels)."""
    xy = _check_points(points)[:, :2].astype(np.float32)
    return np.asarray(cv2.convexHull(xy), dtype=np.float64).reshape(-1, 2)


def head_polygon(points: np.ndarray) -> np.ndarray:
    """(k, 2) float64 convex polygon (image pixels): the face hull widened to the whole head.

    In the face's upright frame (rotated so the outer eye corners, landmarks 33 and 263, lie
    on a horizontal line), about the centre (cx, cy) of the hull's bounding box, each hull
    vertex (x, y) moves to (cx + HEAD_WIDTH (x - cx), cy + k (y - cy)) with k = HEAD_UP above
    the centre and HEAD_DOWN below it; the head is the convex hull of the moved vertices,
    rotated back to the image.
    """
    hull = face_polygon(points)
    local, rot = _upright(np.vstack([_check_points(points)[:, :2], hull]))
    local = local[N_LANDMARKS:]
    lo, hi = local.min(axis=0), local.max(axis=0)
    centre = (lo + hi) / 2
    d = local - centre
    scale = np.where(d[:, 1] < 0, HEAD_UP, HEAD_DOWN)
    moved = centre + np.column_stack([HEAD_WIDTH * d[:, 0], scale * d[:, 1]])
    image = (moved @ rot.T).astype(np.float32)
    return np.asarray(cv2.convexHull(image), dtype=np.float64).reshape(-1, 2)


def polygon_mask(polygon: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """(h, w) bool: pixel centres inside a convex polygon ((k, 2) image pixels), clipped."""
    mask = np.zeros(shape[:2], dtype=np.uint8)
    shift = 4  # sub-pixel vertices: 1/16 pixel
    pts = np.round(np.asarray(polygon) * (1 << shift)).astype(np.int32)
    cv2.fillConvexPoly(mask, pts, 1, lineType=cv2.LINE_8, shift=shift)
    return mask.astype(bool)


def region_masks(points: np.ndarray | None, shape: tuple[int, ...]) -> dict[str, np.ndarray]:
    """The three region masks ((h, w) bool) of a frame of ``shape`` from its landmarks.

    ``points`` None (no face): the face and head masks are empty.
    """
    h, w = shape[:2]
    if points is None:
        empty = np.zeros((h, w), dtype=bool)
        return {"face": empty, "head": empty, "frame": np.ones((h, w), dtype=bool)}
    return {
        "face": polygon_mask(face_polygon(points), shape),
        "head": polygon_mask(head_polygon(points), shape),
        "frame": np.ones((h, w), dtype=bool),
    }


def frame_scores(
    reference: np.ndarray, test: np.ndarray, masks: Mapping[str, np.ndarray]
) -> dict[str, tuple[float, float]]:
    """(SSIM, PSNR dB) of ``test`` against ``reference`` for each named mask."""
    smap = ssim_map(reference, test)
    err = (luma(reference) - luma(test)) ** 2
    out = {}
    for name, mask in masks.items():
        out[name] = (masked_mean(smap, mask), _decibels(masked_mean(err, mask)))
    return out


def aligned(
    outputs: Iterable[np.ndarray | None], count: int | None = None
) -> Iterator[tuple[np.ndarray, bool]]:
    """Output frames 0 .. count-1 by index (without end when ``count`` is None), each with
    True where it is a held frame.

    A None (dropped) frame, or one past the end of ``outputs``, is the previous frame held.
    Frames beyond ``count`` are ignored. Raises ValueError when frame 0 is missing.
    """
    last = None
    it = iter(outputs)
    for i in itertools.count() if count is None else range(count):
        frame = next(it, None)
        if frame is None and last is None:
            raise ValueError(f"output frame {i} is missing and there is no earlier frame to hold")
        if frame is not None:
            last = frame
        assert last is not None
        yield last, frame is None


@dataclass
class QualityReport:
    """Per-frame scores of an output against its input.

    ssim, psnr : region -> one float per frame (nan where the input showed no face; PSNR
        in dB, inf for identical pixels)
    held : number of output frames that were missing and held
    untracked : number of input frames where the tracker found no face
    """

    frames: int = 0
    ssim: dict[str, list[float]] = field(default_factory=lambda: {r: [] for r in REGIONS})
    psnr: dict[str, list[float]] = field(default_factory=lambda: {r: [] for r in REGIONS})
    held: int = 0
    untracked: int = 0

    def add(self, scores: Mapping[str, tuple[float, float]]) -> None:
        self.frames += 1
        for region in REGIONS:
            s, p = scores[region]
            self.ssim[region].append(s)
            self.psnr[region].append(p)

    def mean_ssim(self, region: str) -> float:
        """Mean over frames (those with a face, for the face and head)."""
        return _nanmean(self.ssim[region])

    def mean_psnr(self, region: str) -> float:
        """Mean over frames of each frame's PSNR, capped at PSNR_CAP_DB."""
        return _nanmean(np.minimum(np.asarray(self.psnr[region], dtype=np.float64), PSNR_CAP_DB))

    def as_dict(self) -> dict[str, object]:
        return {
            "frames": self.frames,
            "held": self.held,
            "untracked": self.untracked,
            "ssim": {r: self.mean_ssim(r) for r in REGIONS},
            "psnr_db": {r: self.mean_psnr(r) for r in REGIONS},
        }


def _nanmean(values: list[float] | np.ndarray) -> float:
    a = np.asarray(values, dtype=np.float64)
    a = a[~np.isnan(a)]
    return float(a.mean()) if a.size else math.nan


def read_frames(path: str | Path) -> Iterator[np.ndarray]:
    """BGR frames of a video file, in order."""
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise OSError(f"cannot read video {path}")
    try:
        while True:
            ok, frame = cap.read()
            if not ok:
                return
            yield frame
    finally:
        cap.release()


def score_frames(
    inputs: Iterable[np.ndarray],
    outputs: Iterable[np.ndarray | None],
    landmarks: Iterable[np.ndarray | None],
) -> QualityReport:
    """Scores of output frames against input frames, regions from the input's landmarks.

    inputs : (h, w, 3) BGR frames; outputs : frames of the same size, None for a dropped one
    (an output shorter than the input is held at its last frame); landmarks : (468, 2+) image
    pixels per input frame, None where no face was found.
    """
    report = QualityReport()
    pairs = zip(inputs, landmarks, strict=True)
    # zip stops at the input's end: the endless held output is cut there.
    for i, ((ref, points), (frame, was_held)) in enumerate(
        zip(pairs, aligned(outputs), strict=False)
    ):
        if frame.shape[:2] == padded_size(ref.shape[1], ref.shape[0])[::-1]:
            frame = crop_to(frame, ref.shape)  # an odd-sized input, recorded one pixel larger
        if frame.shape[:2] != ref.shape[:2]:
            raise ValueError(f"output frame {i} is {_size(frame)}, the input is {_size(ref)}")
        report.held += was_held
        report.untracked += points is None
        report.add(frame_scores(ref, frame, region_masks(points, ref.shape)))
    return report


def track_all(
    frames: Iterable[np.ndarray], tracker: LandmarkTracker | None = None
) -> Iterator[np.ndarray | None]:
    """The tracker's landmarks ((468, 3) image pixels, or None) of each frame, in order."""
    if tracker is None:
        from facewire.sender.landmarks import LandmarkTracker

        tracker = LandmarkTracker()
    for frame in frames:
        found = tracker.track(frame)
        yield None if found is None else found.points


def score_videos(
    input_path: str | Path,
    output_path: str | Path,
    tracker: LandmarkTracker | None = None,
    limit: int | None = None,
) -> QualityReport:
    """:func:`score_frames` of two video files, the regions tracked in the input.

    Only the input's first ``limit`` frames are scored (None: all); output frames beyond the
    last scored input frame are ignored.
    """
    outputs = read_frames(output_path)
    first = next(outputs, None)
    if first is None:
        raise ValueError(f"no frames in {output_path}")
    # Two readers of the input walk in step: tee buffers at most a frame.
    for_scores, for_tracking = itertools.tee(itertools.islice(read_frames(input_path), limit))
    report = score_frames(
        for_scores, itertools.chain([first], outputs), track_all(for_tracking, tracker)
    )
    if report.frames == 0:
        raise ValueError(f"no frames in {input_path}")
    return report
