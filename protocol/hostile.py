"""What a receiver says about input it refuses: counted always, logged at most once a second.

A hostile or broken peer can send thousands of refused messages a second; one line each would
flood the log (and the disk under it). :class:`Refusals` counts each refusal by why, and logs
one line per REFUSAL_LOG_S at most, with how many it did not log.
"""

from __future__ import annotations

import logging
import time
from collections import Counter
from collections.abc import Callable

logger = logging.getLogger(__name__)

#: At most one line about refused input per this many seconds.
REFUSAL_LOG_S = 1.0


class Refusals:
    """Counts of refused input by kind (``ignored_sessions``, ``refused_snapshots``, ...)."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.counts: Counter[str] = Counter()
        self._clock = clock
        self._logged_at = -float("inf")
        self._unlogged = 0

    def __getitem__(self, kind: str) -> int:
        return self.counts[kind]

    def refuse(self, kind: str, why: str) -> None:
        """Count one refusal of ``kind``; log ``why`` unless a line went out within 1 s."""
        self.counts[kind] += 1
        now = self._clock()
        if now - self._logged_at < REFUSAL_LOG_S:
            self._unlogged += 1
            return
        more = f" (and {self._unlogged} more refused since the last line)" if self._unlogged else ""
        logger.warning("%s%s", why, more)
        self._logged_at, self._unlogged = now, 0
