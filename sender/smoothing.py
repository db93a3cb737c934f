"""The One Euro filter (Casiez, Roussel & Vogel, CHI 2012): jitter out, little lag.

An exponential low-pass whose cut-off rises with the signal's speed: a still face is smoothed
hard (tracker jitter disappears, and with it the bits it would cost), a fast move passes almost
untouched. Vectorised: one filter state per element of a numpy array.
"""

from __future__ import annotations

import logging
import math

import numpy as np

logger = logging.getLogger(__name__)


def _alpha(cutoff_hz: np.ndarray | float, dt: float) -> np.ndarray | float:
    tau = 1.0 / (2.0 * math.pi * np.asarray(cutoff_hz))
    return 1.0 / (1.0 + tau / dt)


class OneEuroFilter:
    """Smooths a stream of (n,) float arrays sampled at known times.

    min_cutoff_hz : cut-off at rest (lower: smoother, more lag when slow)
    beta : how fast the cut-off rises with speed (units: 1 / (signal unit)); higher: less lag
    d_cutoff_hz : cut-off of the speed estimate
    """

    def __init__(self, min_cutoff_hz: float, beta: float, d_cutoff_hz: float = 1.0) -> None:
        if min_cutoff_hz <= 0 or beta < 0 or d_cutoff_hz <= 0:
            raise ValueError(
                f"need min_cutoff > 0, beta >= 0, d_cutoff > 0; got "
                f"{min_cutoff_hz}, {beta}, {d_cutoff_hz}"
            )
        self.min_cutoff_hz, self.beta, self.d_cutoff_hz = min_cutoff_hz, beta, d_cutoff_hz
        self._x: np.ndarray | None = None
        self._dx: np.ndarray | None = None
        self._t = 0.0

    def reset(self) -> None:
        """Forget the past (a new face, a cut)."""
        self._x = self._dx = None

    def __call__(self, x: np.ndarray, t: float) -> np.ndarray:
        """The filtered value of sample ``x`` taken at time ``t`` (seconds)."""
        x = np.asarray(x, dtype=np.float64)
        if self._x is None or self._dx is None or x.shape != self._x.shape or t <= self._t:
            self._x, self._dx, self._t = x.copy(), np.zeros_like(x), t
            return x.copy()
        dt = t - self._t
        dx = (x - self._x) / dt
        self._dx = self._dx + _alpha(self.d_cutoff_hz, dt) * (dx - self._dx)
        cutoff = self.min_cutoff_hz + self.beta * np.abs(self._dx)
        self._x = self._x + _alpha(cutoff, dt) * (x - self._x)
        self._t = t
        return self._x.copy()
