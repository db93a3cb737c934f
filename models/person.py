"""Where a frame shows a person: MediaPipe's selfie segmentation (models/network.py).

Both ends use it on the snapshot frame. The receiver cuts that frame into the person (hair,
neck, shoulders: carried by the head's motion) and the scene behind (still, or moved by the
camera); the sender follows the camera's motion only on what is not a person. The model sees the
whole frame at 256x144 (landscape; a portrait frame is squeezed into it, which it tolerates)
and gives each pixel a probability; the mask is that, resized to the frame.
"""

from __future__ import annotations

import functools
from importlib import resources
from pathlib import Path

import cv2
import numpy as np

from facewire.models.network import Network, rgb_input

MODEL = "selfie_segmentation_landscape.tflite"
INPUT_SIZE = (256, 144)  # width, height


def model_path(name: str = MODEL) -> Path:
    return Path(str(resources.files("facewire.models") / "data" / name))


@functools.cache
def _net() -> Network:
    return Network(model_path())


def person_mask(frame_bgr: np.ndarray) -> np.ndarray:
    """(h, w) float32 in [0, 1]: how likely each pixel of ``frame_bgr`` shows a person."""
    if frame_bgr.ndim != 3 or frame_bgr.shape[2] != 3 or frame_bgr.dtype != np.uint8:
        raise ValueError(f"expected (h, w, 3) uint8 BGR frame, got {frame_bgr.shape}")
    net = _net()
    scaled = cv2.resize(frame_bgr, INPUT_SIZE, interpolation=cv2.INTER_LINEAR)
    (out,) = net.run(rgb_input(scaled, 1 / 255.0)).values()
    small = out[0, :, :, 0].astype(np.float32)
    h, w = frame_bgr.shape[:2]
    return np.clip(cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR), 0.0, 1.0)
