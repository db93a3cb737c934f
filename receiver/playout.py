"""Playout: when each received frame reaches the screen, and what the screen shows between.

Frames carry their capture time on the sender's clock (``capture_us``, protocol/clock.py). Over
a network they arrive unevenly, and over TCP a lost segment holds up every frame behind it, so
a receiver that draws each frame as it arrives shows the network's jitter as uneven motion.

:class:`JitterBuffer` keys frames by capture time and plays them on a media clock of its own:
a frame captured at c is due at c + offset + delay on the receiver's clock, where ``offset``
is the smallest capture-to-arrival time seen lately (the fastest path, with the two clocks'
difference in it, so the hosts need no common clock) and ``delay`` the time the buffer adds
to cover the jitter: fixed, or adapted to what the network does (the 95th percentile of the
recent capture-to-arrival spread). The clock turns up to MAX_SLEW faster or slower to follow
changes in offset or delay, so motion stays even. The screen ticks at the display rate on a
grid anchored at the first frame's capture time. A tick within half a display interval of a
frame's capture time shows that frame as it is; a tick with no frame due shows a picture
between the frame before and the frame after it (the caller blends them feature by feature,
receiver/interpolation.py). A frame that has not arrived when it is due is never guessed at:
the picture holds, and when late frames come the picture skips to the newest one due. A sender
that fell behind stamps the frames it catches up on late: :class:`SenderFrames` puts them back
on the sender's frame grid. After a gap in the chain (lost packets) nothing is blended across
it: the picture holds until the keyframe that ends the gap is due.

:class:`ArrivalPlayout` is playout delay 0: the newest frame is drawn as soon as it arrives,
frames it overtook are not drawn. Lowest latency, jitter and all.

Both tell the receive loop what to do as :class:`Record` and :class:`Show` steps. The
recording is the screen, one picture per sender frame, so it stays aligned with the sender's
frames: frame i is frame i's own picture when the screen showed it, else the previous picture
again (no packet because nothing changed, lost, or dropped as too late). Pictures shown
between frames are not recorded.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from facewire.protocol.channels import FrameValues

logger = logging.getLogger(__name__)

#: Capture-to-arrival times are kept this long to find the fastest path and the spread.
TRANSIT_WINDOW_US = 10_000_000
#: When every frame of this last stretch took RESYNC_US longer than the fastest of the window,
#: the sender's clock stepped back (or the path changed for good): start the window again.
TRANSIT_RECENT_US = 2_000_000
#: Adaptive delay: this quantile of the recent spread, plus a margin, within the bounds below.
AUTO_QUANTILE = 0.95
AUTO_MARGIN_US = 2_000
AUTO_MIN_US = 5_000
AUTO_MAX_US = 80_000
#: Adaptive delay until AUTO_SAMPLES frames have shown what the network does.
AUTO_START_US = 40_000
AUTO_SAMPLES = 30
#: Largest fixed delay accepted, ms.
MAX_DELAY_MS = 2_000.0
MAX_DISPLAY_FPS = 240.0
#: The media clock runs at most this much faster or slower than real time to follow a new
#: target (5%: invisible in facial motion), reaching it at that rate per second of error.
MAX_SLEW = 0.05
SLEW_HORIZON_US = 1_000_000
#: Further than this from its target, the media clock jumps instead (a stall, a clock step).
RESYNC_US = 500_000
#: Frames over which the sender's frame clock is found (about 2 s at 30 fps).
PHASE_FRAMES = 60
#: The receive loop looks at the network at least this often.
MAX_WAIT_US = 200_000
#: Frames of one datagram drawn at their capture times' spacing, up to this far apart (four
#: frames at 30 fps: the most one datagram carries).
MAX_SPACING_US = 140_000
#: The frames' pace follows the datagrams that carried more than one frame while most of
#: this many last ones did (the sender bundles them), else every datagram's.
BUNDLED_OF = 8
#: The frames' pace on arrival follows the least latency of a datagram's first frame over
#: this long (a path that became slower is followed after it).
SPACING_WINDOW_US = 2_000_000


@dataclass(frozen=True)
class PlayoutSettings:
    """How a receiver plays frames out.

    delay_ms : time the jitter buffer adds, ms; None adapts it to the jitter seen; 0 (the
        default) draws each frame as it arrives (no buffer). Over TCP with loss the spread
        to cover is a lost segment's resend, beyond a conversational delay: measured, the
        buffer cost more latency than the call may add (BENCHMARKS.md, "Playout").
    display_fps : pictures per second on screen; None is the sender's frame rate
    """

    delay_ms: float | None = 0.0
    display_fps: float | None = None

    def __post_init__(self) -> None:
        if self.delay_ms is not None and not 0 <= self.delay_ms <= MAX_DELAY_MS:
            raise ValueError(
                f"playout delay must be 0 to {MAX_DELAY_MS:g} ms, got {self.delay_ms:g}"
            )
        if self.display_fps is not None and not 0 < self.display_fps <= MAX_DISPLAY_FPS:
            raise ValueError(
                f"display rate must be above 0 and at most {MAX_DISPLAY_FPS:g} fps, "
                f"got {self.display_fps:g}"
            )

    def describe(self) -> str:
        delay = "adaptive" if self.delay_ms is None else f"{self.delay_ms:g} ms"
        return "on arrival" if self.delay_ms == 0 else f"delay {delay}"


@dataclass(frozen=True, eq=False)
class Record:
    """Write frame ``seq`` of the recording (after repeating the previous picture for the
    frames before it that sent no packet): ``values``' own picture, or the previous picture
    again when ``values`` is None (the frame came too late and was not shown).
    ``after_gap``: the chain broke before this frame (packets were lost): the frames before
    it froze."""

    seq: int
    values: FrameValues | None
    after_gap: bool = False


@dataclass(frozen=True, eq=False)
class Show:
    """Put a picture on screen: frame ``a`` exactly (``b`` None), or a fraction ``t`` of the
    way from ``a`` to ``b``. ``media_us`` is the instant it shows on the sender's clock;
    ``arrival_us`` when ``a`` arrived, for a frame shown exactly (else None)."""

    a: FrameValues
    b: FrameValues | None
    t: float
    media_us: int
    arrival_us: int | None


Step = Record | Show


class Playout(Protocol):
    """What the receive loop needs of a playout."""

    def push(
        self, values: FrameValues, arrival_us: int, after_gap: bool = False, timed: bool = True
    ) -> None:
        """A decoded frame that arrived at ``arrival_us`` (receiver's clock); ``after_gap``:
        the chain broke since the frame pushed before it; ``timed``: the arrival time is when
        it came (not only when the loop, busy drawing, got to it)."""

    def poll(self, now_us: int) -> list[Step]:
        """What to do now, in order."""

    def wait_us(self, now_us: int) -> int:
        """How long the loop may wait for packets before :meth:`poll` has work."""

    @property
    def pending(self) -> int:
        """Frames received and not played yet."""

    @property
    def delay_us(self) -> int:
        """The delay the buffer aims to add now, µs."""


def make_playout(settings: PlayoutSettings, sender_fps: float) -> Playout:
    """The playout ``settings`` ask for, for a sender at ``sender_fps``."""
    if settings.delay_ms == 0:
        return ArrivalPlayout()
    display_fps = settings.display_fps or sender_fps
    delay_us = None if settings.delay_ms is None else round(settings.delay_ms * 1000)
    return JitterBuffer(delay_us, round(1e6 / display_fps), round(1e6 / sender_fps))


@dataclass(eq=False)
class _Entry:
    values: FrameValues
    capture_us: int  # as the sender meant it (SenderFrames), in frame order
    arrival_us: int
    after_gap: bool

    @property
    def seq(self) -> int:
        return self.values.seq


class ArrivalPlayout:
    """Playout delay 0: each frame is drawn when it arrives, the least latency.

    Frames that arrive together because the sender bundled them in one datagram (protocol
    version 3: one datagram every two frames by default) are drawn one after the other at
    their capture times' spacing, so motion keeps the pace it was captured at: each frame is
    due at its capture time plus the least latency a datagram's first frame had over the last
    SPACING_WINDOW_US (each of them shows as late as the first of a bundle that came at once).
    While most of the last BUNDLED_OF datagrams carried more than one frame, only those count:
    a datagram of one frame among them (a frame whose partner had nothing to send, a keyframe
    that left at once) came a frame interval sooner after its capture than a bundle's first,
    and taken as it is, it made every bundle after it late for two seconds, each drawing only
    its last frame (a quarter of a 1280x720 call's frames were not drawn). A frame that comes
    later than that (the repeat of a lost datagram's frame, with the next frame in the same
    datagram; a stall) is due at once, so the newest frame overtakes it: a loss costs a
    frame's picture, not the latency of the frames after it. Frames that a newer one overtook
    are held in the recording and not drawn.
    """

    def __init__(self) -> None:
        self._new: list[tuple[int, _Entry]] = []  # (when it is due, µs receiver clock, entry)
        self._last_seq = -1
        self._batch_arrival: int | None = None
        self._batch_latency = 0  # arrival minus capture of the last datagram's first frame
        # (arrival, arrival minus capture) of each datagram's first frame, recent ones, the
        # least kept (clocks' offset included, which cancels out): of every datagram, and of
        # those that carried more than one frame.
        self._first: deque[tuple[int, int]] = deque()
        self._first_of_bundles: deque[tuple[int, int]] = deque()
        # Whether each of the last datagrams that carried frames carried more than one.
        self._bundled: deque[bool] = deque(maxlen=BUNDLED_OF)

    @property
    def pending(self) -> int:
        return len(self._new)

    @property
    def delay_us(self) -> int:
        return 0

    def push(
        self, values: FrameValues, arrival_us: int, after_gap: bool = False, timed: bool = True
    ) -> None:
        if values.seq <= self._last_seq:
            logger.debug("frame %d after frame %d: dropped", values.seq, self._last_seq)
            return
        self._last_seq = values.seq
        entry = _Entry(values, values.capture_us, arrival_us, after_gap)
        if arrival_us != self._batch_arrival:  # the first frame of a datagram
            self._batch_arrival = arrival_us
            self._batch_latency = arrival_us - values.capture_us
            self._bundled.append(False)
            _keep_least(self._first, arrival_us, self._batch_latency)
        else:
            self._bundled[-1] = True
            _keep_least(self._first_of_bundles, arrival_us, self._batch_latency)
        _keep_least(self._first_of_bundles, arrival_us, None)  # (only the window moves)
        bundling = 2 * sum(self._bundled) > len(self._bundled)
        least = self._first[0][1]
        if bundling and self._first_of_bundles:
            least = self._first_of_bundles[0][1]
        due = values.capture_us + least
        if not 0 <= due - arrival_us <= MAX_SPACING_US:
            due = arrival_us  # late for its pace, or not a bundle's spacing: drawn now
        self._new.append((due, entry))

    def poll(self, now_us: int) -> list[Step]:
        ready = [entry for due, entry in self._new if due <= now_us]
        if not ready:
            return []
        *overtaken, newest = ready
        # Frames still waiting for their turn that the newest overtook are not drawn either.
        self._new = [(due, e) for due, e in self._new if e.seq > newest.seq]
        steps: list[Step] = [Record(e.seq, None, e.after_gap) for e in overtaken]
        steps.append(Record(newest.seq, newest.values, newest.after_gap))
        steps.append(Show(newest.values, None, 0.0, newest.capture_us, newest.arrival_us))
        return steps

    def wait_us(self, now_us: int) -> int:
        if not self._new:
            return MAX_WAIT_US
        return max(0, min(due for due, _ in self._new) - now_us)


def _keep_least(kept: deque[tuple[int, int]], arrival_us: int, latency: int | None) -> None:
    """Add (``arrival_us``, ``latency``) to ``kept`` (None: add nothing), whose first entry is
    then the least latency of the last SPACING_WINDOW_US (a monotonic queue)."""
    if latency is not None:
        while kept and kept[-1][1] >= latency:
            kept.pop()
        kept.append((arrival_us, latency))
    while kept and kept[0][0] < arrival_us - SPACING_WINDOW_US:
        kept.popleft()


class TransitWindow:
    """Capture-to-arrival times of the recent frames (µs; receiver clock minus sender clock,
    so two hosts' clock offset is in them and cancels out of the spread)."""

    def __init__(self) -> None:
        self._samples: deque[tuple[int, int]] = deque()  # (arrival, transit)
        self.offset = 0  # the fastest transit of the window
        self.spread_quantile = 0  # AUTO_QUANTILE of transit - offset

    def __len__(self) -> int:
        return len(self._samples)

    def add(self, arrival_us: int, transit_us: int) -> None:
        self._samples.append((arrival_us, transit_us))
        while self._samples[0][0] < arrival_us - TRANSIT_WINDOW_US:
            self._samples.popleft()
        transits = np.fromiter((t for _, t in self._samples), np.int64, len(self._samples))
        arrivals = np.fromiter((a for a, _ in self._samples), np.int64, len(self._samples))
        recent = arrivals >= arrival_us - TRANSIT_RECENT_US
        if arrivals[0] < arrival_us - TRANSIT_RECENT_US:
            lowest = int(transits.min())
            if int(transits[recent].min()) - lowest > RESYNC_US:
                logger.info(
                    "frames take %.0f ms longer than before: the sender's clock stepped back "
                    "or the path changed; starting the transit window again",
                    (int(transits[recent].min()) - lowest) / 1000,
                )
                self._samples = deque(s for s, r in zip(self._samples, recent, strict=True) if r)
                transits = transits[recent]
        self.offset = int(transits.min())
        self.spread_quantile = int(np.quantile(transits - self.offset, AUTO_QUANTILE))


class SenderFrames:
    """Capture times a sender meant, from the ones it stamped.

    A sender stamps a frame when it reads it; one that fell behind (a busy machine) reads the
    frames it catches up on late, and stamps them close together, although a camera or a file
    gave them one frame interval apart. Frame seq was meant at phase + seq * frame_us, the
    phase being the earliest of the recent stamps against that grid; a stamp up to one frame
    interval after its grid time is taken as the grid time. A later stamp (the camera skipped
    frames, or the sender stalled for longer) is kept as it is, until the grid moves to it.
    """

    def __init__(self, frame_us: int) -> None:
        self.frame_us = frame_us
        self._phases: deque[int] = deque(maxlen=PHASE_FRAMES)

    def capture_us(self, seq: int, stamp_us: int) -> int:
        self._phases.append(stamp_us - seq * self.frame_us)
        meant = min(self._phases) + seq * self.frame_us
        return meant if stamp_us - meant < self.frame_us else stamp_us


class MediaClock:
    """The sender's time being played, as a function of the receiver's time (both µs). It
    runs at real time, or up to MAX_SLEW faster or slower while it follows its target."""

    def __init__(self, local_us: int, media_us: float) -> None:
        self.local = local_us
        self.media = media_us
        self.rate = 1.0

    def at(self, local_us: int) -> float:
        return self.media + (local_us - self.local) * self.rate

    def local_at(self, media_us: float) -> float:
        return self.local + (media_us - self.media) / self.rate

    def steer(self, local_us: int, target_us: float) -> bool:
        """From ``local_us`` on, run towards ``target_us`` (where the clock should be now);
        True when it jumped there instead (too far to run)."""
        media = self.at(local_us)
        error = target_us - media
        jumped = abs(error) > RESYNC_US
        if jumped:
            logger.info("media clock %+.0f ms from its target: jumping", error / 1000)
            media, self.rate = target_us, 1.0
        else:
            self.rate = 1.0 + max(-MAX_SLEW, min(MAX_SLEW, error / SLEW_HORIZON_US))
        self.local, self.media = local_us, media
        return jumped


class JitterBuffer:
    """Frames played on a media clock ``delay`` behind the fastest path, at the display rate.

    delay_us : the delay the buffer adds; None adapts it (see the module's docstring)
    display_us : the display's frame interval; frame_us : the sender's nominal one
    """

    def __init__(self, delay_us: int | None, display_us: int, frame_us: int) -> None:
        if display_us < 1 or frame_us < 1:
            raise ValueError(f"frame intervals must be >= 1 us, got {display_us}, {frame_us}")
        self.fixed_delay_us = delay_us
        self.display_us = display_us
        self.frame_us = frame_us
        self.ticks_missed = 0  # display ticks passed over: the loop was busy
        self._queue: deque[_Entry] = deque()
        self._current: _Entry | None = None  # the frame last shown as it is
        self._transit = TransitWindow()
        self._sender = SenderFrames(frame_us)
        self._clock: MediaClock | None = None
        self._tick = 0.0  # media time of the next display tick
        self._last_seq = -1

    @property
    def pending(self) -> int:
        return len(self._queue)

    @property
    def delay_us(self) -> int:
        if self.fixed_delay_us is not None:
            return self.fixed_delay_us
        if len(self._transit) < AUTO_SAMPLES:
            return AUTO_START_US
        spread = self._transit.spread_quantile + AUTO_MARGIN_US
        return max(AUTO_MIN_US, min(AUTO_MAX_US, spread))

    def _target(self, local_us: int) -> float:
        return float(local_us - self._transit.offset - self.delay_us)

    def push(
        self, values: FrameValues, arrival_us: int, after_gap: bool = False, timed: bool = True
    ) -> None:
        if values.seq <= self._last_seq:
            logger.debug("frame %d after frame %d: dropped", values.seq, self._last_seq)
            return
        self._last_seq = values.seq
        capture = self._sender.capture_us(values.seq, values.capture_us)
        before = self._queue[-1] if self._queue else self._current
        if before is not None and before.capture_us - RESYNC_US < capture <= before.capture_us:
            capture = before.capture_us + 1  # in frame order (unless the clock stepped back)
        if timed or not len(self._transit):
            # Only arrival times that say when a frame came measure the network's spread.
            self._transit.add(arrival_us, arrival_us - capture)
        logger.debug(
            "frame %d: stamped %+.1f ms from its grid time, capture to arrival %.1f ms "
            "(fastest %.1f), delay %.1f ms",
            values.seq,
            (values.capture_us - capture) / 1000,
            (arrival_us - capture) / 1000,
            self._transit.offset / 1000,
            self.delay_us / 1000,
        )
        self._queue.append(_Entry(values, capture, arrival_us, after_gap))
        if self._clock is None:  # the first frame: due ``delay`` from now
            self._clock = MediaClock(arrival_us, self._target(arrival_us))
            self._tick = float(capture)

    def wait_us(self, now_us: int) -> int:
        if self._clock is None:
            return MAX_WAIT_US
        wait = self._clock.local_at(self._tick) - now_us
        return int(max(0.0, min(float(MAX_WAIT_US), math.ceil(wait))))

    def poll(self, now_us: int) -> list[Step]:
        if self._clock is None:
            return []
        if self._clock.steer(now_us, self._target(now_us)):
            self._tick = self._clock.at(now_us)  # a new grid from where the clock jumped to
        media = self._clock.at(now_us)
        if media < self._tick:
            return []
        behind = int((media - self._tick) // self.display_us)
        if behind:
            self.ticks_missed += behind
            self._tick += behind * self.display_us
        tick = self._tick
        self._tick += self.display_us
        return self._play(tick)

    def _hold_until(self, current: _Entry, following: _Entry) -> float:
        """Until when ``current``'s values stand: frames between the two sent no packet
        (nothing changed), so the last of them, a frame before ``following``, still shows
        them."""
        if following.seq == current.seq + 1:
            return float(current.capture_us)
        return float(max(current.capture_us, following.capture_us - self.frame_us))

    def _play(self, tick: float) -> list[Step]:
        """The steps of the display tick showing media time ``tick``: the newest frame due
        (capture time at most half a display interval ahead) as it is, or a picture between
        the frame shown last and the next one, or nothing new (hold). Frames due before it
        that were not shown (they came late) are dropped: the picture catches up."""
        half = self.display_us / 2
        queue = self._queue
        steps: list[Step] = []
        while len(queue) > 1 and queue[1].capture_us <= tick + half:
            dropped = queue.popleft()
            steps.append(Record(dropped.seq, None, dropped.after_gap))
        show: Show | None = None
        current = self._current
        following = queue[0] if queue else None
        if following is not None and following.capture_us <= tick + half:
            current = self._current = queue.popleft()
            steps.append(Record(current.seq, current.values, current.after_gap))
            show = Show(current.values, None, 0.0, current.capture_us, current.arrival_us)
        elif (
            current is not None
            and following is not None
            and not following.after_gap  # nothing is blended across lost frames
            and tick > self._hold_until(current, following)
        ):
            start = self._hold_until(current, following)
            t = min(1.0, (tick - start) / max(1.0, following.capture_us - start))
            show = Show(current.values, following.values, t, round(tick), None)
        if show is not None:
            steps.append(show)
        if logger.isEnabledFor(logging.DEBUG):
            what = "holding" if show is None else f"{show.a.seq} to {show.b and show.b.seq}"
            logger.debug("tick %.1f ms: %s", tick / 1000, what)
        return steps
