"""Eye contours refined by MediaPipe's eye model, so blinks and wide eyes come through.

The 468-point face model sees the eyes at a few pixels each and barely moves the lids: on
akiyo's blinks (real footage) its lid gap stays at 4 px where the eye is shut, against 6.4 px
open. The eye model (``iris_landmark.tflite``) looks at one eye at a time in a 64x64 crop
and closes the lids to under 1 px there. Its first 71 points (lid contours, the rings around
them and the brow) are the face mesh's 71 eye-region landmarks, in the order of
``EYE_REGION`` (MediaPipe's own mapping; the face's left eye is the mirror image, and the
model sees it flipped so both eyes look like a right eye).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from facewire.models.network import Network, rgb_input
from facewire.sender.detector import model_path

INPUT_SIZE = 64
OUTPUT_LAYER = "output_eyes_contours_and_brows"
# Crop side relative to the distance between the eye's corners (MediaPipe's 2.3).
CROP_SCALE = 2.3

# Face-mesh indices of the eye model's 71 points, for the face's right eye (left in the
# picture): lower lid (9), upper lid (7), then rings outwards and the brow.
EYE_REGION = np.array([
    33, 7, 163, 144, 145, 153, 154, 155, 133, 246, 161, 160, 159, 158, 157, 173,
    130, 25, 110, 24, 23, 22, 26, 112, 243, 247, 30, 29, 27, 28, 56, 190,
    226, 31, 228, 229, 230, 231, 232, 233, 244, 113, 225, 224, 223, 222, 221, 189,
    35, 124, 46, 53, 52, 65, 143, 111, 117, 118, 119, 120, 121, 128, 245,
    156, 70, 63, 105, 66, 107, 55, 193,
])  # fmt: skip
# The same points of the face's left eye (right in the picture): the mirror images.
EYE_REGION_LEFT = np.array([
    263, 249, 390, 373, 374, 380, 381, 382, 362, 466, 388, 387, 386, 385, 384, 398,
    359, 255, 339, 254, 253, 252, 256, 341, 463, 467, 260, 259, 257, 258, 286, 414,
    446, 261, 448, 449, 450, 451, 452, 453, 464, 342, 445, 444, 443, 442, 441, 413,
    265, 353, 276, 283, 282, 295, 372, 340, 346, 347, 348, 349, 350, 357, 465,
    383, 300, 293, 334, 296, 336, 285, 417,
])  # fmt: skip
# Of those, only the lids between the corners are taken: the face model places the corners
# better (against the bundled clip's truth, median error 2 px, the eye model's 4 px) and the
# brows far better (7 px from the eye model, whose crop cuts them).
LIDS = np.array([1, 2, 3, 4, 5, 6, 7, 9, 10, 11, 12, 13, 14, 15])
# Corners of each eye, in the direction the model expects its crop's +x axis: outer to
# inner for the right eye; for the left eye inner to outer, then mirrored.
RIGHT_CORNERS = (33, 133)
LEFT_CORNERS = (362, 263)


def eye_crop(points: np.ndarray, corners: tuple[int, int], mirrored: bool) -> np.ndarray:
    """(2, 3) affine from the model's crop pixels to image pixels for one eye."""
    a, b = points[corners[0], :2], points[corners[1], :2]
    d = b - a
    angle = np.arctan2(d[1], d[0])
    s = CROP_SCALE * float(np.hypot(*d)) / INPUT_SIZE
    c, si = np.cos(angle), np.sin(angle)
    lin = s * np.array([[c, -si], [si, c]])
    if mirrored:
        lin = lin @ np.diag([-1.0, 1.0])
    mid = (INPUT_SIZE - 1) / 2
    t = (a + b) / 2 - lin @ np.array([mid, mid])
    return np.hstack([lin, t[:, None]])


class EyeRefiner:
    """Replaces the 71 eye-region landmarks of each eye with the eye model's (x, y).

    Depth (z) stays the face model's: the eye model's z is relative to its own crop. Each eye
    takes about 1.5 ms on one core.
    """

    def __init__(self, path: str | Path | None = None) -> None:
        self.path = Path(path) if path is not None else model_path("iris_landmark.tflite")
        self.net = Network(self.path)

    def refine(self, frame_bgr: np.ndarray, points: np.ndarray) -> np.ndarray:
        """``points`` ((468, 3) image pixels) with both eye regions refined: a new array."""
        eyes = [
            (EYE_REGION, eye_crop(points, RIGHT_CORNERS, mirrored=False)),
            (EYE_REGION_LEFT, eye_crop(points, LEFT_CORNERS, mirrored=True)),
        ]
        raw = []
        for _, m in eyes:
            patch = cv2.warpAffine(
                frame_bgr,
                m,
                (INPUT_SIZE, INPUT_SIZE),
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_REPLICATE,
            )
            raw.append(self.net.run(rgb_input(patch, 1 / 255.0))[OUTPUT_LAYER].reshape(-1, 3))
        out = np.array(points, dtype=np.float64, copy=True)
        for (ids, m), pts in zip(eyes, raw, strict=True):
            # Continuous model coordinates (pixel i spans [i, i+1)) to OpenCV pixel centres.
            q = pts[:, :2].astype(np.float64) - 0.5
            out[ids[LIDS], :2] = q[LIDS] @ m[:, :2].T + m[:, 2]
        return out
