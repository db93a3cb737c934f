"""A contact sheet of a call: where the reconstruction differs from the input, at a glance.

Rows are frames spread evenly over the call; columns are the input, the reconstruction and a
heat map of their difference (luma, absolute, ``HEAT_GAIN`` times amplified: black where they
agree, through blue and yellow to red where they differ by a quarter of the range or more).
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from facewire.receiver.recorder import at_input_size

logger = logging.getLogger(__name__)

ROWS = 6
HEAT_GAIN = 4
#: Rows are scaled to at most this many pixels high (a 4K call still gives a viewable sheet).
MAX_ROW_HEIGHT = 720


def heat_map(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(h, w, 3) uint8 BGR heat map of the luma difference of two BGR frames of one size."""
    if a.shape != b.shape:
        raise ValueError(f"frames differ in size: {a.shape} and {b.shape}")
    luma = [cv2.cvtColor(x, cv2.COLOR_BGR2GRAY) for x in (a, b)]
    diff = cv2.absdiff(*luma)
    heat = cv2.applyColorMap(cv2.convertScaleAbs(diff, alpha=HEAT_GAIN), cv2.COLORMAP_JET)
    heat[diff == 0] = 0  # exact agreement stays black, not the colour map's dark blue
    return heat


def _frames_at(path: Path, indices: list[int]) -> dict[int, np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    wanted, i = set(indices), 0
    out: dict[int, np.ndarray] = {}
    try:
        while len(out) < len(wanted):
            ok, image = capture.read()
            if not ok:
                break
            if i in wanted:
                out[i] = image
            i += 1
    finally:
        capture.release()
    return out


def write_contact_sheet(source: Path, rebuilt: Path, sheet: Path, count: int) -> int:
    """Write ``sheet`` (PNG) for the first ``count`` frames of ``source`` and ``rebuilt``
    (frame i against frame i); returns the number of rows written."""
    if count < 1:
        raise ValueError("no frames to put on a contact sheet")
    indices = sorted({round(i * (count - 1) / max(ROWS - 1, 1)) for i in range(ROWS)})
    inputs, outputs = _frames_at(source, indices), _frames_at(rebuilt, indices)
    rows = []
    for i in indices:
        if i not in inputs or i not in outputs:
            continue
        a, b = inputs[i], at_input_size(outputs[i], inputs[i].shape)
        row = np.hstack([a, b, heat_map(a, b)])
        scale = min(1.0, MAX_ROW_HEIGHT / row.shape[0])
        if scale < 1.0:
            row = cv2.resize(row, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        cv2.putText(row, f"frame {i}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
        rows.append(row)
    if not rows:
        raise OSError(f"cannot read frames from {source} and {rebuilt} for the contact sheet")
    if not cv2.imwrite(str(sheet), np.vstack(rows)):
        raise OSError(f"cannot write {sheet}")
    logger.info("contact sheet: %d frames in %s", len(rows), sheet)
    return len(rows)
