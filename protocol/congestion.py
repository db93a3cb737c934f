"""The sender's rate control: how much the link carries, from the receiver's reports.

Delay-based, in the spirit of WebRTC's GCC (draft-ietf-rmcat-gcc-02) and NADA (RFC 8698): a
queue that grows is the signal to slow down, long before loss. Each reception report
(protocol/bundle.py, :class:`Report`) names the newest datagram received and when it came on
the receiver's clock. The sender remembers when it sent each datagram, so every report gives
one one-way delay sample, offset by the unknown difference between the two clocks. The
smallest sample of the last BASE_WINDOW_S is the path's own delay (LEDBAT's base delay, RFC
6817); what a sample has above it is queueing.

- Queueing over QUEUE_HIGH_MS, or loss over LOSS_HIGH with some queue (over QUEUE_LOW_MS:
  a full queue drops; loss on a link with no queue is the link's own, which sending less does
  not cure; loss counted over the last LOSS_WINDOW_S, so one lost datagram among the few of a
  report interval is not taken for 20%): the rate falls to DECREASE times what the receiver
  got over the last RATE_WINDOW_S (GCC's decrease; in the call's first second, before there
  is such a window, DECREASE times the estimate), at most once per DECREASE_HOLD_S, so one
  queue is not paid for twice.
- Queueing under QUEUE_LOW_MS and loss under LOSS_LOW: the rate grows by INCREASE a second
  (multiplicatively, as GCC; STARTUP_INCREASE until the first decrease, as NADA's
  accelerated ramp-up, but only up to the rate the join's snapshot came at: past it a thin
  link's tbf bucket hides the excess for seconds, and a 24 kbit/s call grew to 36 before a
  queue of 100 ms cut it), but never past CEILING_FACTOR times what the receiver got plus a
  little (CEILING_HEADROOM_BPS), so a sender that has little to send does not claim a link
  it never tried.
- It starts low (START_RATE_BPS: the face and a little more), and lower still where the
  join's snapshot crossed the link slower than that (:meth:`RateController.on_join`), so the
  first burst of patches or of the full snapshot cannot flood a thin link before the first
  reports come back.
- In between: held.

:class:`RateController` is pure: the transport feeds it reports and sends, and reads ``rate_bps``.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass

from facewire.protocol.datagram import IP_UDP_BYTES

logger = logging.getLogger(__name__)

QUEUE_HIGH_MS = 40.0
QUEUE_LOW_MS = 20.0
LOSS_HIGH = 0.10
LOSS_WINDOW_S = 2.0
#: What the receiver got is measured over about this long: one report interval's bytes come
#: in bursts (tbf's bucket, a datagram and a patch fragment together) and read high.
RATE_WINDOW_S = 1.0
LOSS_LOW = 0.02
DECREASE = 0.85
DECREASE_HOLD_S = 0.5
INCREASE = 0.08  # a second, multiplicative
STARTUP_INCREASE = 0.25
#: The estimate grows to at most this times what the receiver got, plus the headroom (GCC's).
CEILING_FACTOR = 1.5
CEILING_HEADROOM_BPS = 10_000.0
#: What the sender may send at once is less: at most this times what the receiver got lately,
#: plus the headroom (:attr:`RateController.sending_bps`). A call sends little steadily and
#: its patches in bursts; with the estimate alone a burst after a quiet spell went into a thin
#: link at up to 1.7 times its rate (16 kbit/s links were estimated at 27) and the queue
#: reached 400 ms before the reports cut it. Each report lets a burst grow a fifth.
PACE_FACTOR = 1.2
PACE_HEADROOM_BPS = 4_000.0
BASE_WINDOW_S = 30.0
#: The rate never falls below this: the face's own geometry and the headers of a datagram every
#: 100 ms fit in it.
MIN_RATE_BPS = 6_000.0
#: Where the estimate starts before any report: a little more than the face alone costs.
START_RATE_BPS = 16_000.0
#: A join whose snapshot came at more than this (not a thin link) starts ``losing`` too, as
#: if its reports showed loss (one frame a datagram, the second-level repeats), until they
#: have shown CLEAN_START_DATAGRAMS in a row arrive: at 5% loss, datagrams lost before any
#: report said so froze the picture and made the p99 (over 100 ms in 4 calls of 19). A
#: thin link's join is slower (2.4 KB in 0.8 s at 24 kbit/s, 0.4 s at 48), and there one
#: frame a datagram would cost 10 kbit/s of headers. Less than the transport's FAST_JOIN_BPS
#: (the full snapshot at once on TCP): a 40 ms link's draft came at 96-200 kbit/s. Counted
#: in datagrams, not seconds: the first reports come while the receiver builds its decoder,
#: of a heartbeat or two, and 1.5 s of them said nothing (p99 over 100 in 3 calls of 20).
ASSUME_LOSS_JOIN_BPS = 64_000.0
CLEAN_START_DATAGRAMS = 45  # 1.5 s at a datagram a frame
#: Loss (a slow average of the reports') over which the sender repeats each datagram's updates
#: in the next one, and under which it stops.
LOSS_REPEAT_ON = 0.01
LOSS_REPEAT_OFF = 0.002
#: That average's time constant, seconds: a report weighs 1 - exp(-its interval / this), 0.1 at
#: 250 ms, whatever beat the reports come at.
_LOSS_AVERAGE_S = 2.4
#: The sender asks for reports at the faster beat (media_path.HURRY) while the last report
#: showed more than this much queue, ms, while the repeats run (the call's start, a lossy
#: link), and for this long after a cut, seconds: while there is something to follow.
HURRY_QUEUE_MS = QUEUE_LOW_MS / 2
HURRY_AFTER_CUT_S = 2.0
#: Send times kept to match reports against (about 60 s of datagrams at 30 a second).
_SENT_KEPT = 2048


@dataclass
class Estimate:
    """What the last report said, for the stats and the logs."""

    queue_ms: float = 0.0
    loss: float = 0.0
    received_bps: float = 0.0


class RateController:
    """The link's estimated rate in bits per second (``rate_bps``), headers counted."""

    def __init__(self, start_bps: float = START_RATE_BPS) -> None:
        self.rate_bps = start_bps
        self.last = Estimate()
        self.decreases = 0
        # A call starts as if its link lost a little: the updates are repeated until about 5 s
        # of reports have shown none lost, so a loss in the first seconds costs no picture.
        self.loss_average = 1.5 * LOSS_REPEAT_ON
        self.lossy = True
        #: Whether the reports have shown loss since the repeats last stopped; on a fast join,
        #: also the call's start until its reports show none (:meth:`on_join`).
        self.losing = False
        self._clean_datagrams = 0  # reported arrived since the assumption, none lost
        self._assumed = False
        self._join_bps = math.inf  # the rate the join's snapshot came at (on_join)
        self._sent: dict[int, float] = {}  # datagram index (low 32 bits) -> send time, s
        self._order: deque[int] = deque()
        self._base: deque[tuple[float, float]] = deque()  # (time, delay sample) rising
        self._prev: tuple[float, int, int, int] | None = None  # arrival s, highest, rx, bytes
        self._history: deque[tuple[float, int, int]] = deque()  # arrival s, highest, received
        self._bytes: deque[tuple[float, int, int]] = deque()  # arrival s, datagrams, bytes
        self._latest_bps = 0.0  # what the receiver got over the last report's interval
        self._last_decrease = -math.inf
        self._last_update: float | None = None

    @property
    def sending_bps(self) -> float:
        """What may leave now: the estimate, within PACE_FACTOR of what the receiver got (over
        the last second, or the last report's interval if more: a burst that the link
        carries grows by a fifth with each report, not each second)."""
        got = max(self.last.received_bps, self._latest_bps)
        if got <= 0:
            return self.rate_bps
        return min(self.rate_bps, PACE_FACTOR * got + PACE_HEADROOM_BPS)

    def on_join(self, bits: float, seconds: float) -> None:
        """The join's snapshot (or its draft) of ``bits`` came ``seconds`` after the
        receiver first asked: the link's rate, measured before any report. The estimate
        starts at no more than DECREASE times it. On a link no faster than the start, the
        first datagrams (the full snapshot's slices among them) would otherwise fill it and
        build a queue of a third of a second before the first report could cut the rate. A
        fast join starts ``losing`` (ASSUME_LOSS_JOIN_BPS says why)."""
        if bits <= 0 or seconds <= 0:
            return
        self._join_bps = bits / seconds
        if self._join_bps > ASSUME_LOSS_JOIN_BPS and not self.losing:
            # Whatever reports came before (the path opens before the snapshot is in: few
            # datagrams, heartbeats) say little of loss.
            self.losing = self._assumed = True
            self._clean_datagrams = 0
        if self._prev is not None:
            return  # the reports know the rate better
        self.rate_bps = max(MIN_RATE_BPS, min(self.rate_bps, DECREASE * self._join_bps))
        logger.debug(
            "rate starts at %.1f kbit/s: the snapshot's %d bytes came in %.0f ms",
            self.rate_bps / 1000, bits // 8, seconds * 1000,
        )  # fmt: skip

    def wants_reports(self, now: float) -> bool:
        """Whether the reports should come at the faster beat now: at the call's start and
        on a lossy link (the repeats run), with a queue, or soon after a cut. On a clean link
        with nothing to follow, half as many reports cost half as much (at 58 bytes each,
        0.9 kbit/s of a 14 kbit/s call)."""
        return (
            self.lossy
            or self.last.queue_ms > HURRY_QUEUE_MS
            or now - self._last_decrease < HURRY_AFTER_CUT_S
        )

    def on_sent(self, index: int, now: float) -> None:
        """A datagram of ``index`` left at ``now`` (seconds, sender's clock)."""
        key = index & 0xFFFFFFFF
        self._sent[key] = now
        self._order.append(key)
        while len(self._order) > _SENT_KEPT:
            self._sent.pop(self._order.popleft(), None)

    def on_report(
        self, now: float, highest: int, arrival_ms: int, received: int, received_bytes: int
    ) -> None:
        """A reception report (the fields of bundle.Report) came at ``now``."""
        sent_at = self._sent.get(highest & 0xFFFFFFFF)
        if sent_at is None:
            return  # a datagram this sender does not remember: nothing to learn
        arrival_s = arrival_ms / 1000.0
        delay = arrival_s - sent_at  # plus the clocks' offset
        while self._base and self._base[-1][1] >= delay:
            self._base.pop()
        self._base.append((now, delay))
        while now - self._base[0][0] > BASE_WINDOW_S:
            self._base.popleft()
        queue_ms = (delay - self._base[0][1]) * 1000.0
        prev, self._prev = self._prev, (arrival_s, highest, received, received_bytes)
        if prev is None:
            self.last = Estimate(queue_ms, 0.0, 0.0)
            self._last_update = now
            return
        span = arrival_s - prev[0]
        expected = (highest - prev[1]) & 0xFFFFFFFF
        got = (received - prev[2]) & 0xFFFFFFFF
        if span <= 0 or expected == 0 or expected > 1 << 20:
            return  # nothing new arrived since the last report (or a report came twice)
        if not self._history:
            self._history.append(prev[:3])
        self._history.append((arrival_s, highest, received))
        while len(self._history) > 2 and arrival_s - self._history[1][0] >= LOSS_WINDOW_S:
            self._history.popleft()
        then = self._history[0]
        window_expected = (highest - then[1]) & 0xFFFFFFFF
        window_got = (received - then[2]) & 0xFFFFFFFF
        window_loss = max(0.0, 1.0 - window_got / window_expected) if window_expected else 0.0
        loss = max(0.0, 1.0 - got / expected)
        self.loss_average += (1.0 - math.exp(-span / _LOSS_AVERAGE_S)) * (loss - self.loss_average)
        if self.loss_average > LOSS_REPEAT_ON:
            self.lossy = True
        elif self.loss_average < LOSS_REPEAT_OFF:
            self.lossy = self.losing = False
        if loss > 0 and self.lossy:
            self.losing, self._assumed = True, False
        elif self._assumed:
            self._clean_datagrams += expected
            if self._clean_datagrams >= CLEAN_START_DATAGRAMS:
                self.losing = self._assumed = False
        if not self._bytes:
            self._bytes.append((prev[0], prev[2], prev[3]))
        self._bytes.append((arrival_s, received, received_bytes))
        while len(self._bytes) > 2 and arrival_s - self._bytes[1][0] >= RATE_WINDOW_S:
            self._bytes.popleft()
        since, count_then, bytes_then = self._bytes[0]
        # The report counts UDP payloads; the rate counts what crossed the link, as the
        # budget does: each datagram's IP and UDP headers too (28 of a 90-byte datagram).
        wire = ((received_bytes - bytes_then) & 0xFFFFFFFF) + IP_UDP_BYTES * (
            (received - count_then) & 0xFFFFFFFF
        )
        received_bps = wire * 8.0 / (arrival_s - since)
        latest = ((received_bytes - prev[3]) & 0xFFFFFFFF) + IP_UDP_BYTES * got
        self._latest_bps = latest * 8.0 / span
        self.last = Estimate(queue_ms, window_loss, received_bps)
        # Over less than RATE_WINDOW_S (the call's first second) what got through says little
        # of what the link carries: a cut then is taken from the estimate, not from it.
        measured = arrival_s - since >= RATE_WINDOW_S
        self._update(now, queue_ms, window_loss, received_bps, measured)

    def _update(
        self, now: float, queue_ms: float, loss: float, received_bps: float, measured: bool
    ) -> None:
        dt = 0.0 if self._last_update is None else min(1.0, now - self._last_update)
        self._last_update = now
        if queue_ms > QUEUE_HIGH_MS or (loss > LOSS_HIGH and queue_ms > QUEUE_LOW_MS):
            if now - self._last_decrease >= DECREASE_HOLD_S:
                self._last_decrease = now
                self.decreases += 1
                got = received_bps if measured else self.rate_bps
                self.rate_bps = max(MIN_RATE_BPS, min(self.rate_bps, DECREASE * got))
                logger.debug(
                    "rate down to %.1f kbit/s (queue %.0f ms, loss %.0f%%)",
                    self.rate_bps / 1000, queue_ms, loss * 100,
                )  # fmt: skip
            return
        if queue_ms < QUEUE_LOW_MS and loss < LOSS_LOW:
            ceiling = CEILING_FACTOR * received_bps + CEILING_HEADROOM_BPS
            startup = not self.decreases and self.rate_bps < self._join_bps
            increase = STARTUP_INCREASE if startup else INCREASE
            grown = self.rate_bps * (1.0 + increase * dt)
            self.rate_bps = max(self.rate_bps, min(grown, ceiling))
