"""How far the face the call draws is from the face the tracker saw, frame by frame.

Two distances per tracked frame, RMS over the face's points in image pixels:

- ``fit``: the wire fit (seed 000's least squares, all wire parameters, unquantised) against
  the tracked points: what the rig cannot express;
- ``sent``: the face the receiver rebuilds from the frame's quantised values (the wire basis,
  smoothing and quantisation on top of the fit) against the tracked points.
"""

from __future__ import annotations

from array import array

import numpy as np


def rms_px(a: np.ndarray, b: np.ndarray) -> float:
    """RMS over points of the image-plane (x, y) distance between (n, 2+) point sets."""
    d = np.asarray(a, np.float64)[:, :2] - np.asarray(b, np.float64)[:, :2]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


class FitResidual:
    """The per-frame residuals of one session (float32 each: a long call stays small)."""

    def __init__(self) -> None:
        self.seqs = array("l")
        self.fit = array("f")
        self.sent = array("f")

    def add(self, seq: int, tracked: np.ndarray, fitted: np.ndarray, sent: np.ndarray) -> None:
        self.seqs.append(seq)
        self.fit.append(rms_px(fitted, tracked))
        self.sent.append(rms_px(sent, tracked))

    def __len__(self) -> int:
        return len(self.seqs)

    def summary(self, per_frame: bool = True) -> dict[str, object]:
        """Median, 90th percentile and largest of each, px (None without a tracked frame);
        with ``per_frame`` every frame's ``[seq, fit, sent]`` too."""
        out: dict[str, object] = {"frames": len(self)}
        for name, values in (("fit_px", self.fit), ("sent_px", self.sent)):
            v = np.asarray(values, np.float64)
            out[name] = (
                None
                if len(v) == 0
                else {
                    "median": float(np.median(v)),
                    "p90": float(np.percentile(v, 90)),
                    "max": float(v.max()),
                }
            )
        if per_frame:
            out["per_frame"] = [
                [int(s), round(float(f), 3), round(float(x), 3)]
                for s, f, x in zip(self.seqs, self.fit, self.sent, strict=True)
            ]
        return out
