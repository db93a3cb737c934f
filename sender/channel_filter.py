"""Temporal filters on the sender's channel values, before quantisation.

The landmark tracker jitters by about a quantisation step from frame to frame (on the bundled
clip 1.8 steps RMS on the head's rotation, against 0.7 of true motion), and coding that jitter
was most of the geometry bit rate. A One Euro filter (Casiez, Roussel & Vogel, CHI 2012) per
value removes it: a low cutoff while a value is still, rising with its speed so that a moving
one follows with little lag.

Values are filtered in quantisation steps (value / step). A step is a fixed distance on screen
(docs/protocol.md section 6.4), so one set of settings suits any call size, and speeds are in
steps per second. Each kind of motion gets its own settings:

- the head's position (translation) moves every pixel of the face, so it has a high cutoff and
  a speed estimate that reacts within a few frames: lag there costs the most picture quality;
- its rotation, a high cutoff too, with a steadier speed estimate;
- its scale (distance to the camera) and the camera's motion change slowly: low cutoffs;
- the expression (the wire basis, and any channel without settings of its own) is still most
  of the time and moves in bursts, so its cutoff is low at rest and opens fast with speed: a
  blink keeps its depth.

The settings were chosen against the bundled clip's ground truth (rebuilt markers, blink
depth) and against real clips' pictures (face SSIM of a call, benchmarks/bench_quality.py);
docs/what-we-tried.md, "Smoothing before quantisation", has the figures.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from facewire.models.body import BODY
from facewire.models.camera import CAMERA
from facewire.models.face_channels import POSE_ROTATION, POSE_SCALE, POSE_TRANSLATION

logger = logging.getLogger(__name__)

#: A pause longer than this (the face was lost) restarts the filters: no smoothing across it.
MAX_GAP_S = 0.5


@dataclass(frozen=True)
class OneEuroSettings:
    """min_cutoff : Hz at rest; beta : Hz of cutoff per step/s of speed; d_cutoff : Hz of the
    speed estimate."""

    min_cutoff: float
    beta: float
    d_cutoff: float

    def __post_init__(self) -> None:
        if not (self.min_cutoff > 0 and self.d_cutoff > 0 and self.beta >= 0):
            raise ValueError(f"One Euro settings need min_cutoff, d_cutoff > 0, beta >= 0: {self}")


TRANSLATION = OneEuroSettings(min_cutoff=4.0, beta=1.0, d_cutoff=4.0)
ROTATION = OneEuroSettings(min_cutoff=4.0, beta=1.0, d_cutoff=1.0)
SLOW = OneEuroSettings(min_cutoff=1.0, beta=0.2, d_cutoff=4.0)
EXPRESSION = OneEuroSettings(min_cutoff=1.0, beta=0.3, d_cutoff=10.0)
#: Settings by channel name; channels not listed get ``EXPRESSION``.
SETTINGS = {
    POSE_TRANSLATION: TRANSLATION,
    POSE_ROTATION: ROTATION,
    POSE_SCALE: SLOW,
    CAMERA: SLOW,
    BODY: SLOW,
}


def _alpha(cutoff_hz: np.ndarray | float, dt: float) -> np.ndarray:
    """Smoothing factor of a first-order low-pass with ``cutoff_hz`` at sample interval ``dt``."""
    tau = 1.0 / (2.0 * np.pi * np.asarray(cutoff_hz, dtype=np.float64))
    return np.asarray(1.0 / (1.0 + tau / dt))


class OneEuro:
    """One Euro filter of a (k,) vector, one cutoff per element (from its own speed)."""

    def __init__(self, settings: OneEuroSettings) -> None:
        self.settings = settings
        self._x: np.ndarray | None = None
        self._velocity = np.zeros(0)

    def __call__(self, x: np.ndarray, dt: float | None) -> np.ndarray:
        """Filtered ``x``; ``dt`` seconds since the last sample, None to start again."""
        if self._x is None or dt is None or self._x.shape != x.shape:
            self._x, self._velocity = x.copy(), np.zeros_like(x)
            return x.copy()
        s = self.settings
        # The signed velocity is filtered before its size raises the cutoff: jitter averages
        # out in it, a steady motion does not.
        raw = (x - self._x) / dt
        self._velocity = self._velocity + _alpha(s.d_cutoff, dt) * (raw - self._velocity)
        a = _alpha(s.min_cutoff + s.beta * np.abs(self._velocity), dt)
        self._x = self._x + a * (x - self._x)
        return self._x.copy()


class ChannelSmoother:
    """Filters one session's channel values frame by frame, in units of their steps.

    steps : channel name -> quantisation step (the session's channel table)
    settings : channel name -> filter settings, for channels other than ``SETTINGS`` says;
        None there: the channel is not filtered
    """

    def __init__(
        self,
        steps: Mapping[str, float],
        settings: Mapping[str, OneEuroSettings | None] | None = None,
    ) -> None:
        for name, step in steps.items():
            if not (np.isfinite(step) and step > 0):
                raise ValueError(f"channel {name!r}: step must be finite and > 0, got {step}")
        table = {**SETTINGS, **(settings or {})}
        self.steps = dict(steps)
        self._filters = {}
        for name in self.steps:
            chosen = table.get(name, EXPRESSION)
            if chosen is not None:
                self._filters[name] = OneEuro(chosen)
        self._t: float | None = None

    def reset(self) -> None:
        """Forget the past: the next values pass through unchanged."""
        self._t = None

    def __call__(self, values: Mapping[str, np.ndarray], t: float) -> dict[str, np.ndarray]:
        """Filtered copies of ``values`` (name -> (k,) float) sampled at ``t`` seconds.

        Channels without a step or a filter pass through unchanged.
        """
        dt = None if self._t is None else t - self._t
        if dt is not None and not 0 < dt <= MAX_GAP_S:
            dt = None  # a pause, a restart or a clock step: start again from these values
        self._t = t
        out = {}
        for name, v in values.items():
            x = np.asarray(v, dtype=np.float64)
            if name not in self._filters:
                out[name] = x.copy()
                continue
            step = self.steps[name]
            out[name] = self._filters[name](x / step, dt) * step
        return out
