"""The camera's motion as a protocol channel: where two of the snapshot frame's corners are now.

A handheld or car-mounted camera shakes, so the whole background shifts by several pixels
from the snapshot frame. A similarity (shift, roll, zoom: snapshot frame -> this frame)
describes that motion of a distant or flat scene; it has four degrees of freedom. On the
wire it is the ``camera`` channel: the displacement in pixels of the frame's top-left and
bottom-right corners (x, y each), which fix the similarity. That parametrisation is bounded
and in screen units: see :func:`camera_step` for the step. (Until 2026-11-23 all four
corners went, a general homography's eight values for a motion that has four.)
"""

from __future__ import annotations

import numpy as np

from facewire.models.face_channels import HYSTERESIS

CAMERA = "camera"
CAMERA_SIZE = 4
#: Worst displacement (per axis) inside the frame of a similarity over that of its two
#: corners' values: 2 (:func:`camera_step`).
CORNER_GAIN = 2.0


def frame_corners(width: int, height: int) -> np.ndarray:
    """(2, 2) float64 corner pixel centres: top-left, bottom-right."""
    return np.array([[0.0, 0.0], [width - 1.0, height - 1.0]])


def corners_from_homography(homography: np.ndarray, width: int, height: int) -> np.ndarray:
    """(4,) corner displacements (px) of a (3, 3) homography of a width x height frame (a
    similarity's, to be exact)."""
    corners = frame_corners(width, height)
    h = np.asarray(homography, np.float64)
    moved = np.column_stack([corners, np.ones(2)]) @ h.T
    return (moved[:, :2] / moved[:, 2:] - corners).ravel()


def homography_from_corners(displacement: np.ndarray, width: int, height: int) -> np.ndarray:
    """(3, 3) similarity taking the two corners to corners + ``displacement`` (4,)."""
    d = np.asarray(displacement, dtype=np.float64)
    if d.shape != (CAMERA_SIZE,):
        raise ValueError(f"expected ({CAMERA_SIZE},) corner displacements, got {d.shape}")
    corners = frame_corners(width, height)
    p = corners[:, 0] + 1j * corners[:, 1]
    moved = corners + d.reshape(2, 2)
    q = moved[:, 0] + 1j * moved[:, 1]
    a = (q[1] - q[0]) / (p[1] - p[0])  # rotation and zoom
    b = q[0] - a * p[0]  # shift
    return np.array([[a.real, -a.imag, b.real], [a.imag, a.real, b.imag], [0.0, 0.0, 1.0]])


def camera_step(error_px: float) -> float:
    """Quantisation step of the corner displacements for an error budget in pixels.

    With the quantiser's hysteresis each value is up to (0.5 + HYSTERESIS) steps off, a
    corner up to sqrt(2) times that. A point z of the frame (complex, the top-left corner
    0, the bottom-right 1) moves by e0 (1 - z) + e1 z for corner errors e0, e1, and inside
    the rectangle |1 - z| + |z| <= sqrt(2): so no pixel moves further than CORNER_GAIN = 2
    times a value's error (checked in tests/test_camera.py).
    """
    return error_px / ((0.5 + HYSTERESIS) * CORNER_GAIN)
