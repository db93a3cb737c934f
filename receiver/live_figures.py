"""A call's figures as they are now: bit rate per channel, pictures per second and latency
over the last few seconds, for a live view to show beside the picture.

The receive loop hands every picture it shows to :meth:`LiveFigures.add` (cheap: a few
numbers into a bounded deque under a lock); :meth:`LiveFigures.as_dict` is called from
another thread (a web server's) and does the arithmetic.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Rates and latency are over the pictures shown in the last WINDOW_S seconds.
WINDOW_S = 2.0
#: At most this many pictures are remembered (a 240 fps display over 2 s).
MAX_SAMPLES = 480
#: A latency outside 0..MAX_LATENCY_MS means the two ends do not share a clock (two machines):
#: it is not shown.
MAX_LATENCY_MS = 60_000.0
#: How many status lines (session began, ended...) are kept.
MAX_EVENTS = 8


@dataclass(frozen=True)
class _Sample:
    t: float  # monotonic seconds, when the picture was shown
    bytes_received: dict[str, int]
    latency_ms: float
    frames_out: int


class LiveFigures:
    """Figures over the last WINDOW_S seconds of pictures shown. Thread-safe."""

    def __init__(self, clock: Any = time.monotonic) -> None:
        self._clock = clock
        self._lock = threading.Lock()
        self._samples: deque[_Sample] = deque(maxlen=MAX_SAMPLES)
        self._events: deque[str] = deque(maxlen=MAX_EVENTS)
        self._session: tuple[int, int, int] | None = None  # id, width, height
        self._pictures = 0

    def add(
        self,
        session_id: int,
        size: tuple[int, int],
        bytes_received: dict[str, int],
        latency_ms: float,
        frames_out: int,
    ) -> None:
        """A picture was shown now. ``size`` is (width, height); ``bytes_received`` the
        payload bytes per channel since the call began."""
        sample = _Sample(self._clock(), dict(bytes_received), latency_ms, frames_out)
        with self._lock:
            if self._session is None or self._session[0] != session_id:
                self._samples.clear()  # a new session: its rates start afresh
            self._session = (session_id, *size)
            self._samples.append(sample)
            self._pictures += 1

    def event(self, line: str) -> None:
        """A line a person watching wants to know ("session ended (bye) after 300 frames")."""
        with self._lock:
            self._events.append(line)

    def as_dict(self) -> dict[str, Any]:
        """The figures now, JSON-ready.

        ``fps``: pictures shown per second; ``kbps``: payload kbit/s received per channel and
        ``total``; ``latency_ms``: capture to screen, median and max (None when the ends do
        not share a clock); ``age_s``: seconds since the last picture (None before the
        first). Rates are over the last WINDOW_S seconds, 0 when nothing came in it.
        """
        now = self._clock()
        with self._lock:
            samples = [s for s in self._samples if now - s.t <= WINDOW_S]
            last = self._samples[-1] if self._samples else None
            session, pictures, events = self._session, self._pictures, list(self._events)
        figures: dict[str, Any] = {
            "session": None,
            "pictures": pictures,
            "frames": last.frames_out if last else 0,
            "age_s": round(now - last.t, 3) if last else None,
            "fps": 0.0,
            "kbps": {},
            "latency_ms": None,
            "events": events,
        }
        if session is not None:
            figures["session"] = {"id": session[0], "width": session[1], "height": session[2]}
        if last is not None:
            # Totals since the call began; rates need two pictures in the window.
            figures["kbps"] = {name: 0.0 for name in last.bytes_received} | {"total": 0.0}
        if len(samples) >= 2:
            first, newest = samples[0], samples[-1]
            span = newest.t - first.t
            if span > 0:
                figures["fps"] = round((len(samples) - 1) / span, 1)
                kbps = {
                    name: (count - first.bytes_received.get(name, 0)) * 8 / 1000 / span
                    for name, count in newest.bytes_received.items()
                }
                kbps["total"] = sum(kbps.values())
                figures["kbps"] = {name: round(v, 2) for name, v in kbps.items()}
        latencies = np.asarray([s.latency_ms for s in samples])
        if latencies.size and ((latencies >= 0) & (latencies < MAX_LATENCY_MS)).all():
            figures["latency_ms"] = {
                "p50": round(float(np.median(latencies)), 1),
                "max": round(float(latencies.max()), 1),
            }
        return figures
