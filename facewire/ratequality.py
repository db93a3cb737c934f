"""Rate-quality curves: a codec's best quality at a rate, and the rate it needs for a quality.

A codec is measured at several target rates and frame sizes (the resolution ladder). A call
that adapts would send, at each rate, the size that looks best, so a codec's curve is the
upper envelope of all its points: sorted by rate, a point stays only if its quality beats
every point at a lower rate. Between two points of the envelope, quality is interpolated
linearly in log-rate; nothing is extrapolated beyond the rates measured.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable
from dataclasses import dataclass

logger = logging.getLogger(__name__)

Point = tuple[float, float]  # (bit rate, quality)


def envelope(points: Iterable[Point]) -> list[Point]:
    """The upper envelope of (rate, quality) points, in increasing rate (a quality that is nan
    or None, as the JSON writes nan, left out)."""
    best: list[Point] = []
    known = (p for p in points if p[1] is not None and not math.isnan(p[1]) and p[0] > 0)
    for rate, quality in sorted(known):
        if not best or quality > best[-1][1]:
            if best and best[-1][0] == rate:
                best.pop()
            best.append((rate, quality))
    return best


def quality_at(curve: list[Point], rate: float) -> float:
    """The envelope's quality at ``rate``; nan outside the rates measured."""
    if not curve or rate < curve[0][0] or rate > curve[-1][0]:
        return math.nan
    for (r0, q0), (r1, q1) in zip(curve, curve[1:], strict=False):
        if r0 <= rate <= r1:
            t = math.log(rate / r0) / math.log(r1 / r0)
            return q0 + t * (q1 - q0)
    return curve[0][1]  # a single point, at exactly its rate


@dataclass(frozen=True)
class RateNeeded:
    """The rate a codec needs to reach a quality.

    bound : "=" reached at ``rate`` (interpolated); "<=" already reached at its lowest rate
        measured (``rate``), so it may need less; ">" not reached at its highest (``rate``)
    """

    rate: float
    bound: str

    def times(self, ours: float) -> float:
        return self.rate / ours


def rate_for(curve: list[Point], quality: float) -> RateNeeded | None:
    """The lowest rate at which the envelope reaches ``quality``; None without points."""
    if not curve or math.isnan(quality):
        return None
    if curve[0][1] >= quality:
        return RateNeeded(curve[0][0], "<=")
    for (r0, q0), (r1, q1) in zip(curve, curve[1:], strict=False):
        if q0 < quality <= q1:
            t = (quality - q0) / (q1 - q0)
            return RateNeeded(math.exp(math.log(r0) + t * math.log(r1 / r0)), "=")
    return RateNeeded(curve[-1][0], ">")
