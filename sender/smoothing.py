"""Temporal smoothing of tracked points: the One Euro filter (Casiez, Roussel & Vogel, CHI 2012).

A first-order low-pass filter whose cutoff rises with the signal's speed: a still point gets
a low cutoff (jitter removed), a fast one a high cutoff (little lag). Per frame and point:

    alpha(fc, dt) = 1 / (1 + 1 / (2 pi fc dt))
    v   = lowpass(|x - x_hat_prev| / dt, alpha(d_cutoff, dt))       speed, filtered
    fc  = min_cutoff + beta * v / scale
    x_hat = lowpass(x, alpha(fc, dt))

``LandmarkSmoother`` measures speed in face sizes per second (``scale`` is the points' RMS
distance from their centroid in the image plane, about 0.4 of the face's width), so the same
settings suit a face 50 px wide and one 500 px wide.
"""

from __future__ import annotations

import logging

import numpy as np

logger = logging.getLogger(__name__)

# Chosen with benchmarks/bench_smoothing.py (BENCHMARKS.md, "Tracking"): about
# half the jitter on still faces, at most half a frame of lag on the fastest moves. A lower
# beta or cutoff removes more jitter but lags a frame or more; a higher beta removes little.
MIN_CUTOFF_HZ = 1.0
BETA = 3.0
D_CUTOFF_HZ = 5.0


def alpha(cutoff_hz: np.ndarray | float, dt: float) -> np.ndarray:
    """Smoothing factor of a first-order low-pass with ``cutoff_hz`` at sample interval ``dt``."""
    tau = 1.0 / (2.0 * np.pi * np.asarray(cutoff_hz, dtype=np.float64))
    return np.asarray(1.0 / (1.0 + tau / dt))


class OneEuroFilter:
    """One Euro filter over (n, d) arrays: one speed (and cutoff) per row, shared by its d
    coordinates, so a point moves along a straight line, not one axis after the other.

    min_cutoff : Hz, the cutoff of a still point (lower: less jitter, more lag when slow)
    beta : how fast the cutoff rises with speed, Hz per (scale unit per second)
    d_cutoff : Hz, cutoff of the speed estimate itself
    """

    def __init__(
        self,
        min_cutoff: float = MIN_CUTOFF_HZ,
        beta: float = BETA,
        d_cutoff: float = D_CUTOFF_HZ,
    ) -> None:
        if not (min_cutoff > 0 and d_cutoff > 0 and beta >= 0):
            raise ValueError(
                f"expected min_cutoff > 0, d_cutoff > 0, beta >= 0; got {min_cutoff}, "
                f"{d_cutoff}, {beta}"
            )
        self.min_cutoff = min_cutoff
        self.beta = beta
        self.d_cutoff = d_cutoff
        self.reset()

    def reset(self) -> None:
        """Forget the past: the next sample passes through unchanged."""
        self._x: np.ndarray | None = None
        self._speed: np.ndarray | None = None
        self._t: float | None = None

    def __call__(self, x: np.ndarray, t: float, scale: float = 1.0) -> np.ndarray:
        """Filtered copy of ``x`` ((n, d) float) sampled at time ``t`` (seconds).

        ``scale`` divides the speed before it raises the cutoff (e.g. a face's size in
        pixels, so that speeds are in face sizes per second).
        """
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2:
            raise ValueError(f"expected (n, d) float array, got {x.shape}")
        if not scale > 0:
            raise ValueError(f"expected positive scale, got {scale}")
        if self._x is None or self._t is None or self._speed is None:
            self._x, self._t = x.copy(), t
            self._speed = np.zeros(len(x))
            return x.copy()
        if x.shape != self._x.shape:
            raise ValueError(f"expected {self._x.shape} like the last sample, got {x.shape}")
        dt = t - self._t
        if not dt > 0:
            # A repeated or out-of-order timestamp: nothing to learn about speed.
            return self._x.copy()
        raw_speed = np.linalg.norm(x - self._x, axis=1) / dt
        self._speed = self._speed + alpha(self.d_cutoff, dt) * (raw_speed - self._speed)
        cutoff = self.min_cutoff + self.beta * self._speed / scale
        a = alpha(cutoff, dt)[:, None]
        self._x = self._x + a * (x - self._x)
        self._t = t
        return self._x.copy()


def face_scale(points: np.ndarray) -> float:
    """RMS distance (px) of the points from their centroid, in the image plane (x, y)."""
    xy = np.asarray(points, dtype=np.float64)[:, :2]
    return float(np.sqrt(((xy - xy.mean(axis=0)) ** 2).sum(axis=1).mean()))


class LandmarkSmoother:
    """One Euro filter on a face's landmarks ((n, 3) image points), speeds in face sizes.

    Call it once per frame; :meth:`reset` when the face is lost or another face is taken.
    ``fps`` times the frames whose caller gives no timestamp.
    """

    def __init__(
        self,
        min_cutoff: float = MIN_CUTOFF_HZ,
        beta: float = BETA,
        d_cutoff: float = D_CUTOFF_HZ,
        fps: float = 30.0,
    ) -> None:
        if not fps > 0:
            raise ValueError(f"expected positive fps, got {fps}")
        self.filter = OneEuroFilter(min_cutoff, beta, d_cutoff)
        self.fps = fps
        self._t: float | None = None

    def reset(self) -> None:
        self.filter.reset()
        self._t = None

    def __call__(self, points: np.ndarray, t: float | None = None) -> np.ndarray:
        """Smoothed (n, 3) points; ``t`` in seconds, None: one frame after the last call."""
        if t is None:
            t = 0.0 if self._t is None else self._t + 1.0 / self.fps
        self._t = t
        scale = face_scale(points)
        return self.filter(points, t, scale if scale > 0 else 1.0)
