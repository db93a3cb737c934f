"""Holes in an image filled from their surroundings, smoothly (push-pull).

Where nothing is known (a texel the camera never saw, the scene behind a person), each
unknown pixel takes the mask-weighted average of the nearest coarser pyramid level that has
data there: a smooth blend that continues the hole's borders. Telea or Navier-Stokes
inpainting draws the border's colours into the hole along rays, and a hole the size of a
head or a person comes out as a star of streaks.
"""

from __future__ import annotations

import cv2
import numpy as np


def fill_invalid(image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill pixels where ``valid`` is False from their valid neighbours (push-pull).

    image : (h, w, c) or (h, w) uint8; valid : (h, w) bool.
    Valid pixels are kept; each invalid one takes the mask-weighted average of the
    nearest coarser pyramid level that has data there, so holes get smooth colours that
    continue their borders (and a texture's bilinear sampling at UV seams never reads black).
    """
    img = np.asarray(image)
    if valid.shape != img.shape[:2]:
        raise ValueError(f"expected valid of shape {img.shape[:2]}, got {valid.shape}")
    if valid.all():
        return img.copy()
    if not valid.any():
        return np.zeros_like(img)
    squeeze = img.ndim == 2
    data = img.astype(np.float32)
    if squeeze:
        data = data[:, :, None]
    w = valid.astype(np.float32)

    # Push: mask-weighted downsampling until one texel is left.
    levels: list[tuple[np.ndarray, np.ndarray]] = []
    acc: np.ndarray = data * w[:, :, None]
    wt: np.ndarray = w
    while True:
        levels.append((acc, wt))
        h, wd = wt.shape
        if h == 1 and wd == 1:
            break
        size = (max(1, (wd + 1) // 2), max(1, (h + 1) // 2))
        acc = cv2.resize(acc, size, interpolation=cv2.INTER_AREA)
        wt = cv2.resize(wt, size, interpolation=cv2.INTER_AREA)
        if acc.ndim == 2:
            acc = acc[:, :, None]

    # Pull: from the coarsest level down, fill each level's empty texels from the level
    # above it (already filled), upsampled bilinearly.
    acc, wt = levels[-1]
    filled = acc / np.maximum(wt, 1e-12)[:, :, None]
    for acc, wt in reversed(levels[:-1]):
        h, wd = wt.shape
        up = cv2.resize(filled, (wd, h), interpolation=cv2.INTER_LINEAR)
        if up.ndim == 2:
            up = up[:, :, None]
        # Partly covered texels blend their own average with the coarser estimate.
        a = np.clip(wt, 0.0, 1.0)[:, :, None]
        own = acc / np.maximum(wt, 1e-12)[:, :, None]
        filled = a * own + (1.0 - a) * up

    out = np.where(valid[:, :, None], data, filled)
    out = np.clip(out + 0.5, 0, 255).astype(np.uint8)
    return out[:, :, 0] if squeeze else out
