"""Quantisation of channel values to integers (pure numpy).

A value ``x`` with step ``d`` travels as the integer ``q`` and comes back as ``q * d``.
Plain rounding (``q = rint(x / d)``) errs by at most ``d / 2``. With ``hysteresis`` h and the
previous frame's integers, a value keeps its level until it is more than ``0.5 + h`` steps
away from it: noise smaller than that never changes an integer, so a still face costs no bits,
and the error grows to at most ``(0.5 + h) d``.
"""

from __future__ import annotations

import logging

import numpy as np
from numpy.typing import ArrayLike, NDArray

from facewire.protocol.constants import MAX_CHANNEL_VALUE

logger = logging.getLogger(__name__)


def _steps(step: float | ArrayLike, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """Validate a scalar or per-element step and broadcast it to ``shape``."""
    steps = np.asarray(step, dtype=np.float64)
    if not np.all(np.isfinite(steps)) or not np.all(steps > 0):
        raise ValueError(f"quantisation steps must be finite and > 0, got {step!r}")
    try:
        return np.broadcast_to(steps, shape)
    except ValueError:
        raise ValueError(
            f"step of shape {steps.shape} does not broadcast to values of shape {shape}"
        ) from None


def quantise(
    values: ArrayLike,
    step: float | ArrayLike,
    previous: ArrayLike | None = None,
    hysteresis: float = 0.0,
) -> tuple[NDArray[np.int64], int]:
    """Quantise floats to integers in [-MAX_CHANNEL_VALUE, MAX_CHANNEL_VALUE].

    Parameters
    ----------
    values : (...) float array, any units
    step : float or array broadcastable to ``values``, same units, > 0
    previous : integers of the previous frame (same shape), for the hysteresis
    hysteresis : >= 0, in steps

    Returns
    -------
    q : int64 array, same shape as ``values``
    clipped : how many values were outside the representable range and were clipped
    """
    x = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(x)):
        bad = int(np.count_nonzero(~np.isfinite(x)))
        raise ValueError(f"cannot quantise non-finite values ({bad} of {x.size})")
    if hysteresis < 0:
        raise ValueError(f"hysteresis must be >= 0, got {hysteresis}")
    scaled = x / _steps(step, x.shape)
    q = np.rint(scaled)
    if previous is not None:
        prev = np.asarray(previous)
        if prev.shape != x.shape:
            raise ValueError(f"previous values of shape {prev.shape}, expected {x.shape}")
        q = np.where(np.abs(scaled - prev) <= 0.5 + hysteresis, prev, q)
    out_of_range = np.abs(q) > MAX_CHANNEL_VALUE
    clipped = int(np.count_nonzero(out_of_range))
    if clipped:
        logger.debug("quantise: %d of %d values clipped", clipped, x.size)
    return np.clip(q, -MAX_CHANNEL_VALUE, MAX_CHANNEL_VALUE).astype(np.int64), clipped


def dequantise(q: ArrayLike, step: float | ArrayLike) -> NDArray[np.float64]:
    """Inverse of :func:`quantise`: ``q * step`` as float64 with the shape of ``q``."""
    qa = np.asarray(q)
    if not np.issubdtype(qa.dtype, np.integer):
        raise ValueError(f"expected an integer array, got dtype {qa.dtype}")
    return qa.astype(np.float64) * _steps(step, qa.shape)
