"""Image helpers shared by the rendering and texture tests."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

W, H = 640, 480
# PNGs the tests save so a person can look at them.
OUT = Path(os.environ.get("FACEWIRE_TEST_OUT", "/tmp/facewire-tests"))


def save(name: str, img: np.ndarray) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(OUT / name), img)


def gradient_background() -> np.ndarray:
    yy, xx = np.mgrid[0:H, 0:W]
    return np.dstack([60 + xx / 8, 70 + yy / 6, 140 + 0 * xx]).astype(np.uint8)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return float(10 * np.log10(255.0**2 / max(mse, 1e-12)))
