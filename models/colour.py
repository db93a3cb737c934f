"""Colour adaptation of seed 003 section 2.3 (Eq. 2): the model's texture takes on the colour
of the live video, so a live patch merges without a seam.

The reference colour is the skin's, measured by HSV histogram analysis inside the REMs: the
peak of the hue histogram, and the mean saturation and value of the texels around that peak
(:func:`reference_colour`). Eq. 2 then moves every texel of the model's texture:

    H <- H + (H_peak,video - H_peak,model)      (degrees, around the circle)
    S <- S * (S_mean,video / S_mean,model)      (clipped to [0, 1])
    V <- V * (V_mean,video / V_mean,model)      (clipped to [0, 1])

(:func:`adapt`). H is in degrees [0, 360), S and V in [0, 1] (OpenCV's float HSV).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

logger = logging.getLogger(__name__)

#: Width of a hue histogram bin, degrees.
HUE_BIN_DEG = 2.0
#: Texels taken as the reference colour: hue within this of the peak ...
HUE_WINDOW_DEG = 20.0
#: ... and neither grey nor dark (sclera, iris, lashes and shadow are not skin).
MIN_SATURATION = 0.06
MIN_VALUE = 0.12
#: Fewer reference texels than this and there is no reference colour to measure.
MIN_TEXELS = 16


@dataclass(frozen=True)
class ColourStats:
    """A region's reference colour: hue peak (degrees, [0, 360)), mean saturation and value."""

    h_peak: float
    s_mean: float
    v_mean: float


def to_hsv(bgr: np.ndarray) -> np.ndarray:
    """(..., 3) float32 H (degrees), S, V of a uint8 BGR image."""
    img = np.asarray(bgr)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"expected (h, w, 3) uint8 BGR, got {img.shape} {img.dtype}")
    return cv2.cvtColor(img.astype(np.float32) / 255.0, cv2.COLOR_BGR2HSV)


def to_bgr(hsv: np.ndarray) -> np.ndarray:
    """uint8 BGR of a float32 HSV image (H degrees, S and V in [0, 1])."""
    bgr = cv2.cvtColor(np.ascontiguousarray(hsv, dtype=np.float32), cv2.COLOR_HSV2BGR)
    return np.clip(bgr * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _hue_distance(h: np.ndarray, peak: float) -> np.ndarray:
    d = np.abs(h - peak) % 360.0
    return np.minimum(d, 360.0 - d)


def reference_colour(hsv: np.ndarray, mask: np.ndarray | None = None) -> ColourStats | None:
    """The skin's reference colour inside ``mask`` (seed 003 section 2.3.1, steps 2-3).

    hsv : (h, w, 3) float32 from :func:`to_hsv`; mask : (h, w) bool or None (all texels).
    The hue histogram (HUE_BIN_DEG bins, smoothed around the circle) of the coloured,
    lit texels gives the peak; S and V are averaged over those within HUE_WINDOW_DEG of it.
    None when fewer than MIN_TEXELS texels qualify.
    """
    a = np.asarray(hsv, dtype=np.float32)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected (h, w, 3) HSV, got {a.shape}")
    pixels = a.reshape(-1, 3) if mask is None else a[np.asarray(mask, dtype=bool)]
    lit = pixels[(pixels[:, 1] >= MIN_SATURATION) & (pixels[:, 2] >= MIN_VALUE)]
    if len(lit) < MIN_TEXELS:
        return None
    bins = int(round(360.0 / HUE_BIN_DEG))
    hist = np.bincount((lit[:, 0] / HUE_BIN_DEG).astype(np.int64) % bins, minlength=bins)
    smooth = 2 * hist + np.roll(hist, 1) + np.roll(hist, -1)  # [1 2 1] around the circle
    peak = (int(np.argmax(smooth)) + 0.5) * HUE_BIN_DEG
    near = lit[_hue_distance(lit[:, 0], peak) <= HUE_WINDOW_DEG]
    return ColourStats(peak, float(near[:, 1].mean()), float(near[:, 2].mean()))


def adapt(hsv: np.ndarray, model: ColourStats, video: ColourStats) -> np.ndarray:
    """Eq. 2: the model's texture ``hsv`` (float32 HSV) moved from ``model``'s reference
    colour to ``video``'s; returns uint8 BGR."""
    out = np.array(hsv, dtype=np.float32, copy=True)
    out[..., 0] = (out[..., 0] + (video.h_peak - model.h_peak)) % 360.0
    out[..., 1] = np.clip(out[..., 1] * (video.s_mean / max(model.s_mean, 1e-6)), 0.0, 1.0)
    out[..., 2] = np.clip(out[..., 2] * (video.v_mean / max(model.v_mean, 1e-6)), 0.0, 1.0)
    return to_bgr(out)
