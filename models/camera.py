"""The camera's motion as a protocol channel: where the snapshot frame's corners are now.

A handheld or car-mounted camera shakes, so the whole background shifts by several pixels
from the snapshot frame. A homography (snapshot frame -> this frame) describes that motion of
a distant or flat scene. On the wire it is the ``camera`` channel: the displacement in pixels
of the frame's four corners (x, y each; top-left, top-right, bottom-right, bottom-left). That
parametrisation is bounded and in screen units: see :func:`camera_step` for the step.
"""

from __future__ import annotations

import cv2
import numpy as np

from models.face_channels import HYSTERESIS

CAMERA = "camera"
CAMERA_SIZE = 8
#: Worst interior displacement (per axis) of a homography over that of its corners.
CORNER_GAIN = 2.23


def frame_corners(width: int, height: int) -> np.ndarray:
    """(4, 2) float32 corner pixel centres: top-left, top-right, bottom-right, bottom-left."""
    w, h = width - 1, height - 1
    return np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=np.float32)


def corners_from_homography(homography: np.ndarray, width: int, height: int) -> np.ndarray:
    """(8,) corner displacements (px) of a (3, 3) homography of a width x height frame."""
    corners = frame_corners(width, height)
    moved = cv2.perspectiveTransform(corners[None], np.asarray(homography, np.float64))[0]
    return (moved - corners).astype(np.float64).ravel()


def homography_from_corners(displacement: np.ndarray, width: int, height: int) -> np.ndarray:
    """(3, 3) homography taking the frame's corners to corners + ``displacement`` (8,)."""
    d = np.asarray(displacement, dtype=np.float64)
    if d.shape != (CAMERA_SIZE,):
        raise ValueError(f"expected ({CAMERA_SIZE},) corner displacements, got {d.shape}")
    corners = frame_corners(width, height)
    moved = (corners + d.reshape(4, 2)).astype(np.float32)
    return np.asarray(cv2.getPerspectiveTransform(corners, moved), dtype=np.float64)


def camera_step(error_px: float) -> float:
    """Quantisation step of the corner displacements for an error budget in pixels.

    With the quantiser's hysteresis each corner is up to (0.5 + HYSTERESIS) steps off. An
    affine motion moves no pixel inside the frame further than its corners, but corners off
    independently make a general homography, which moves interior pixels up to CORNER_GAIN
    times as far along an axis (every corner at its limit; checked in tests/test_camera.py).
    """
    return error_px / ((0.5 + HYSTERESIS) * CORNER_GAIN)
