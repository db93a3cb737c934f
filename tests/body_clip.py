"""Clips of a person whose whole body moves, made from real frames.

A real frame is cut into the person (the segmentation of models/person.py) and the scene
behind (the person painted out), and the person is put back scaled and shifted about a point
(the face), while the scene stays: a person leaning back from the camera (shrinking) or
moving sideways, which a camera's zoom or pan would not show (it moves the scene too). The
painted-out scene is a smooth guess where the person was; at a scale of 1 or more about a
point inside the person, the person put back covers most of it.
"""

from __future__ import annotations

import cv2
import numpy as np

from facewire.models.person import person_mask

#: Where the segmentation is above this, the pixel is the person's.
PERSON = 0.5


def eased(t: float) -> float:
    """0 -> 1 smoothly (smoothstep) as ``t`` goes 0 -> 1; held outside."""
    t = min(max(t, 0.0), 1.0)
    return t * t * (3.0 - 2.0 * t)


def moved_person(
    frame: np.ndarray, centre: tuple[float, float], scale: float, shift: tuple[float, float]
) -> np.ndarray:
    """``frame`` (h, w, 3) uint8 with its person scaled by ``scale`` about ``centre`` (x, y,
    pixels) and then shifted by ``shift``, over the scene with the person painted out."""
    h, w = frame.shape[:2]
    alpha = person_mask(frame)
    hard = (alpha > 0.2).astype(np.uint8)
    grown = cv2.dilate(hard, np.ones((7, 7), np.uint8))
    scene = cv2.inpaint(frame, grown, 5, cv2.INPAINT_TELEA)
    cx, cy = centre
    m = np.array(
        [[scale, 0.0, cx - scale * cx + shift[0]], [0.0, scale, cy - scale * cy + shift[1]]]
    )
    # The person continues past the frame's bottom and sides: replicated, as a body would.
    person = cv2.warpAffine(
        frame, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    weight = cv2.warpAffine(
        alpha, m, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    weight = weight[..., None]
    out = weight * person.astype(np.float32) + (1.0 - weight) * scene.astype(np.float32)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def leaning_clip(
    frames: list[np.ndarray],
    centre: tuple[float, float],
    scale: tuple[float, float] = (1.3, 1.0),
    shift: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 0.0), (0.0, 0.0)),
    moving: int = 60,
) -> list[np.ndarray]:
    """``frames`` with the person going from ``scale[0]`` and ``shift[0]`` to ``scale[1]`` and
    ``shift[1]`` over the first ``moving`` frames (eased), then held."""
    out = []
    for i, frame in enumerate(frames):
        t = eased(i / max(moving, 1))
        s = scale[0] + t * (scale[1] - scale[0])
        d = tuple(a + t * (b - a) for a, b in zip(shift[0], shift[1], strict=True))
        out.append(moved_person(frame, centre, s, d))  # type: ignore[arg-type]
    return out


def silhouette(frame: np.ndarray) -> np.ndarray:
    """(h, w) bool: where the segmentation sees a person in ``frame``."""
    return person_mask(frame) > PERSON


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two bool masks (1 when both are empty)."""
    union = np.logical_or(a, b).sum()
    return float(np.logical_and(a, b).sum() / union) if union else 1.0
