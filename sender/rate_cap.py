"""The geometry's rate cap: a token bucket over the frame packets' bytes.

The geometry's payload must stay within its budget (1.5 kbit/s) on any footage, and what it
costs follows the face: a talking head at 30 fps sends 1.2-1.45 kbit/s, a fast handheld
shot (foreman) twice that. Over the budget, a frame's packet is held back: the receiver
keeps drawing the last frame it has, as it does for a frame that needed no packet, and the
next packet carries the motion since (one delta over several frames costs less than one
per frame, headers included). Before it comes to that, the quantiser's hysteresis widens as
the bucket runs low (:meth:`RateCap.slack`): a value then moves only for a larger change, so
a face in motion sends fewer, coarser changes instead of losing whole frames, and a still one
keeps the fine steps. Keyframes and frames that carry a REM patch always go; the
bucket may then run into debt, which the frames after it wait out. Over any stretch of T
seconds the packets carry at most ``GEOMETRY_KBPS * T`` plus the bucket's BUCKET_S seconds
(and the keyframes and patch frames' debt, paid back by the frames after them).
"""

from __future__ import annotations

#: Payload budget of the frame packets, kbit/s (DESIGN.md: all geometry at most 1.5).
GEOMETRY_KBPS = 1.5
#: Budget of the face's edge corrections (sender/edge.py), kbit/s: their share of the frame
#: packets they ride in is taken from a bucket of their own, so they never hold the face back.
EDGE_KBPS = 0.75
#: Budget of the body's motion (sender/body_motion.py), kbit/s, a bucket of its own as the
#: edge's: paid from the face's, a person swaying in their chair cost Miss America 0.005 face
#: SSIM (0.32 kbit/s of the face's 1.5).
BODY_KBPS = 0.25
#: Most the bucket holds, seconds of budget: a burst of motion this long goes at full rate.
BUCKET_S = 2.0
#: What it holds at the start, seconds of budget: the session's first keyframe (about 30-40
#: bytes), so the first frames after it need not wait.
START_S = 0.25
#: Below this many seconds of budget in the bucket, the quantiser's hysteresis widens ...
LOW_S = 0.5
#: ... by up to this many steps, when the bucket is empty (the most a value then errs is
#: 0.5 + HYSTERESIS + SLACK_STEPS steps).
SLACK_STEPS = 1.0


class RateCap:
    """Token bucket of ``kbps`` at ``fps`` frames per second, START_S full at the start."""

    def __init__(self, kbps: float, fps: float, bucket_s: float = BUCKET_S) -> None:
        if not (kbps > 0 and fps > 0 and bucket_s > 0):
            raise ValueError(f"rate {kbps} kbit/s, {fps} fps and bucket {bucket_s} s must be > 0")
        self.fps, self.bucket_s = fps, bucket_s
        self.slack_steps = SLACK_STEPS
        self.tokens = 0.0
        self.set_rate(kbps)
        self.tokens = min(self.capacity, kbps * 1000.0 / 8.0 * START_S)
        #: Frames whose packet was held back.
        self.held = 0

    def set_rate(self, kbps: float) -> None:
        """Fill at ``kbps`` from now on (0: not at all), holding ``bucket_s`` of it."""
        self.per_frame = max(0.0, kbps) * 1000.0 / 8.0 / self.fps
        self.low = max(0.0, kbps) * 1000.0 / 8.0 * LOW_S
        self.capacity = max(0.0, kbps) * 1000.0 / 8.0 * self.bucket_s
        self.tokens = min(self.tokens, self.capacity)

    def slack(self) -> float:
        """Steps of hysteresis the quantiser adds for the next frame: none while the bucket
        holds LOW_S of budget or more, rising linearly to ``slack_steps`` as it empties."""
        if self.low <= 0:  # no budget at all
            return self.slack_steps
        return self.slack_steps * min(1.0, max(0.0, 1.0 - self.tokens / self.low))

    def next_frame(self) -> bool:
        """Add a frame's worth of bytes; whether the frame's packet may go."""
        self.tokens = min(self.capacity, self.tokens + self.per_frame)
        return self.tokens > 0

    def spend(self, nbytes: float) -> None:
        """Take a sent packet's bytes (into debt if need be)."""
        self.tokens -= nbytes
