"""How evenly pictures reach the screen: the figures in which network jitter shows.

A receiver notes, for every picture it puts on screen, when it was ready (its own clock) and
which instant of the sender's capture it shows. From these:

- the intervals between pictures (even playout: all one display interval);
- the motion jitter: the spread of (time between two pictures on screen) - (time between the
  instants they show). Zero when motion plays at the pace it was captured, whatever the
  network did;
- repeats and skips on a screen refreshing at the display rate: a refresh that shows the same
  picture as the refresh before it (a stutter), and a picture replaced before any refresh
  showed it (a dropped frame). The refreshes are placed midway between picture times of an
  even playout, so a picture a little early or late is not counted as either.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

import numpy as np

logger = logging.getLogger(__name__)


def display_figures(shown: Sequence[tuple[int, int]], refresh_us: float) -> dict:
    """Figures of the pictures ``shown``: (ready, depicted) µs each, in screen order, on a
    screen refreshing every ``refresh_us``. Times in the result are ms."""
    if len(shown) < 2 or not refresh_us > 0:
        return {
            "pictures": len(shown),
            "interval_ms": {"p50": 0.0, "std": 0.0, "p99": 0.0},
            "motion_jitter_ms": 0.0,
            "repeated": 0,
            "skipped": 0,
        }
    ready = np.array([r for r, _ in shown], np.float64)
    depicted = np.array([d for _, d in shown], np.float64)
    intervals = np.diff(ready) / 1000.0
    motion = intervals - np.diff(depicted) / 1000.0
    refreshes = ready[0] + (np.arange(int((ready[-1] - ready[0]) // refresh_us)) + 0.5) * (
        refresh_us
    )
    visible = np.searchsorted(ready, refreshes, side="right") - 1  # picture up at each refresh
    repeated = int(np.count_nonzero(np.diff(visible) == 0))
    seen = np.unique(visible)
    skipped = int(seen[-1] + 1 - len(seen)) if len(seen) else 0
    return {
        "pictures": len(shown),
        "interval_ms": {
            "p50": float(np.percentile(intervals, 50)),
            "std": float(intervals.std()),
            "p99": float(np.percentile(intervals, 99)),
        },
        "motion_jitter_ms": float(motion.std()),
        "repeated": repeated,
        "skipped": skipped,
    }
