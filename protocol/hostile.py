"""What a receiver says about input it refuses: at most one line a second.

A hostile or broken peer can send thousands of refused messages a second; one line each would
flood the log (and the disk under it). The refusals themselves are counted where they happen
(the transport's and the receiver's figures); :class:`Refusals` only says so, one line per
REFUSAL_LOG_S at most, with how many it did not say.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

logger = logging.getLogger(__name__)

#: At most one line about refused input per this many seconds.
REFUSAL_LOG_S = 1.0


class Refusals:
    """The log of refused input, one line a second at most."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self._clock = clock
        self._logged_at = -float("inf")
        self._unlogged = 0

    def refuse(self, why: str) -> None:
        """Log ``why``, unless a line went out within REFUSAL_LOG_S (then count it)."""
        now = self._clock()
        if now - self._logged_at < REFUSAL_LOG_S:
            self._unlogged += 1
            return
        more = f" (and {self._unlogged} more refused since the last line)" if self._unlogged else ""
        logger.warning("%s%s", why, more)
        self._logged_at, self._unlogged = now, 0
