"""Which frames came late: waited behind a lost TCP segment, not just the network's delay.

A frame's delay from capture to arrival is compared with the fastest frame of the last
``window_s``. The two ends' clocks need not agree: their offset is in every delay and cancels,
and the window follows a slow drift between them. A frame more than ``late_ms`` slower than
that was held up on its way (on a lossy link: a retransmission, a round trip or more), and the
receiver asks the sender for the second path (protocol/transport.py).
"""

from __future__ import annotations

from collections import deque

from facewire.protocol.constants import LATE_FRAME_MS, LATE_WINDOW_S


class LateFrames:
    """Judges each frame's arrival against the fastest of the recent ones."""

    def __init__(self, late_ms: float = LATE_FRAME_MS, window_s: float = LATE_WINDOW_S) -> None:
        self._late_us = late_ms * 1000
        self._window_us = window_s * 1e6
        # (arrival_us, delay_us) with increasing delays: the first is the window's fastest.
        self._fastest: deque[tuple[int, int]] = deque()

    def late(self, arrival_us: int, capture_us: int) -> bool:
        """Whether a frame captured at ``capture_us`` (sender's clock) that arrived at
        ``arrival_us`` (receiver's clock) came late; it joins the window either way."""
        delay = arrival_us - capture_us
        fastest = self._fastest
        while fastest and fastest[0][0] < arrival_us - self._window_us:
            fastest.popleft()
        late = bool(fastest) and delay - fastest[0][1] > self._late_us
        while fastest and fastest[-1][1] >= delay:
            fastest.pop()
        fastest.append((arrival_us, delay))
        return late
