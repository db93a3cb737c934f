"""The sender's delay-based rate control, fed synthetic send times and reception reports."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import pytest

from facewire.protocol.bundle import Report
from facewire.protocol.congestion import (
    CEILING_FACTOR,
    CEILING_HEADROOM_BPS,
    CLEAN_START_DATAGRAMS,
    DECREASE,
    DECREASE_HOLD_S,
    MIN_RATE_BPS,
    QUEUE_HIGH_MS,
    START_RATE_BPS,
    RateController,
)
from facewire.protocol.datagram import IP_UDP_BYTES

T0 = 100.0  # the sender's clock at the start, s
FPS = 20  # datagrams a second: 5 in each report interval
SIZE = 122  # UDP payload bytes of each: with IP's and UDP's 28, 24 kbit/s when none is lost
RECEIVED_BPS = (SIZE + IP_UDP_BYTES) * 8 * FPS


@dataclass
class Step:
    """The controller after one report."""

    now: float
    rate_bps: float
    decreases: int
    queue_ms: float
    loss: float
    received_bps: float


def simulate(
    controller: RateController,
    seconds: float,
    *,
    delay: Callable[[float], float] = lambda t: 0.05,
    lost: Callable[[int], bool] = lambda n: False,
    offset_s: float = 0.0,
    report_every: float = 0.25,
    index0: int = 70_000,
    extra: Callable[[RateController, float], None] | None = None,
) -> list[Step]:
    """Datagrams sent at FPS from T0 (one-way ``delay(send time)``, ``lost(n)`` never arrive),
    the receiver's report every ``report_every`` (its clock ``offset_s`` ahead), each reaching
    the sender 10 ms later. ``extra(controller, now)`` runs before each report."""
    sends = [(T0 + n / FPS, index0 + n) for n in range(int(seconds * FPS))]
    arrivals = sorted((t + delay(t), n) for n, (t, _) in enumerate(sends) if not lost(n))
    steps: list[Step] = []
    sent = got = 0
    received = nbytes = 0
    highest = arrived_at = None
    k = 1
    while True:
        at = T0 + k * report_every + 0.1  # the receiver's report, its time on the sender's clock
        if at > T0 + seconds:
            return steps
        while sent < len(sends) and sends[sent][0] <= at + 0.01:
            controller.on_sent(sends[sent][1], sends[sent][0])
            sent += 1
        while got < len(arrivals) and arrivals[got][0] <= at:
            arrival, n = arrivals[got]
            got += 1
            received += 1
            nbytes += SIZE
            if highest is None or sends[n][1] > highest:
                highest, arrived_at = sends[n][1], arrival
        k += 1
        if highest is None:
            continue
        now = at + 0.01
        if extra is not None:
            extra(controller, now)
        wire = Report(highest, round((arrived_at + offset_s) * 1000), received, nbytes)
        report = Report.parse(bytes(wire))
        controller.on_report(
            now, report.highest, report.arrival_ms, report.received, report.received_bytes
        )
        last = controller.last
        steps.append(
            Step(now, controller.rate_bps, controller.decreases, last.queue_ms, last.loss,
                 last.received_bps)
        )  # fmt: skip


def growing_queue(since: float, per_s: float = 0.1) -> Callable[[float], float]:
    """50 ms, then ``per_s`` more every second from ``since`` s after the start."""
    return lambda t: 0.05 + max(0.0, t - T0 - since) * per_s


def every_fifth(n: int) -> bool:
    return n % 5 == 2


#: A steady path, a queue that starts to grow after 2 s, one datagram in five lost.
SCENARIOS: list[dict[str, Any]] = [{}, {"delay": growing_queue(since=2)}, {"lost": every_fifth}]


def test_starts_low_a_little_above_the_face() -> None:
    assert RateController().rate_bps == START_RATE_BPS == 16_000


@pytest.mark.parametrize(
    ("nbytes", "seconds", "start_kbit"),
    [
        (2208, 1.37, 0.85 * 2208 * 8 / 1.37 / 1000),  # Claire's draft over a 16 kbit/s link
        (2208, 0.05, 16.0),  # a fast link: the start stands
        (2208, 30.0, 6.0),  # never under the floor
    ],
)
def test_the_joins_snapshot_sets_where_the_rate_starts(
    nbytes: int, seconds: float, start_kbit: float
) -> None:
    controller = RateController()
    controller.on_join(nbytes * 8, seconds)
    assert controller.rate_bps / 1000 == pytest.approx(start_kbit)
    assert controller.sending_bps == controller.rate_bps  # before any report, all of it


def test_the_joins_snapshot_counts_for_nothing_once_reports_came() -> None:
    controller = RateController()
    simulate(controller, 3)
    before = controller.rate_bps
    controller.on_join(2208 * 8, 1.37)
    assert controller.rate_bps == before


def test_stable_delay_no_loss_grows_up_to_its_ceiling() -> None:
    controller = RateController(start_bps=20_000)
    steps = simulate(controller, 40)
    ceiling = CEILING_FACTOR * RECEIVED_BPS + CEILING_HEADROOM_BPS
    assert steps[0].received_bps == 0  # the first report only starts the count
    assert all(s.received_bps == pytest.approx(RECEIVED_BPS, rel=0.01) for s in steps[1:])
    assert all(s.queue_ms == pytest.approx(0, abs=1) and s.loss == 0 for s in steps)
    rates = [s.rate_bps for s in steps]
    assert rates == sorted(rates)  # never falls
    after_2s = next(s.rate_bps for s in steps if s.now >= T0 + 2)
    assert 20_000 * 1.5 < after_2s < 20_000 * 1.75  # about 25% a second before any decrease
    assert max(rates) <= CEILING_FACTOR * max(s.received_bps for s in steps) + 10_000 + 1e-6
    assert rates[-1] == pytest.approx(ceiling, rel=0.02)
    assert ceiling == pytest.approx(46_000)  # GCC's 1.5 x 24 + 10
    # What may leave at once: 1.2 x 24 + 4, so a burst of patches after a quiet spell does
    # not go into a thin link at nearly twice what it was seen to carry.
    assert controller.sending_bps == pytest.approx(32_800, rel=0.02)
    assert controller.decreases == 0


def test_past_the_rate_the_join_came_at_the_start_grows_as_after_a_cut() -> None:
    """A thin link's tbf bucket hides a rate above the link's for seconds (no queue in the
    reports); grown at 25% a second past it, a 24 kbit/s call reached 36 kbit/s and a queue
    of 100 ms before the first cut. The join's snapshot measured the link: past its rate
    the start grows at 8% a second, as after a cut."""
    joined, plain = RateController(), RateController()
    joined.on_join(2300 * 8, 0.8)  # 23 kbit/s
    rates: dict[str, list[float]] = {"joined": [], "plain": []}
    simulate(joined, 5, extra=lambda c, now: rates["joined"].append(c.rate_bps))
    simulate(plain, 5, extra=lambda c, now: rates["plain"].append(c.rate_bps))
    assert rates["joined"][3] == pytest.approx(rates["plain"][3])  # both under 23 at 25%/s
    assert plain.rate_bps > 40_000
    assert 23_000 < joined.rate_bps < 23_000 * 1.08**4


def test_a_burst_grows_a_fifth_a_report_to_the_estimate() -> None:
    """A sender that sent 12 kbit/s and now has patches to send: what may leave grows with
    each report while the link carries it (1.2 x what came + 4 kbit/s), up to the estimate,
    in about 1.5 s."""
    controller = RateController(start_bps=64_000)
    index = got = nbytes = 0
    t, allowed = T0, []
    for report in range(12):
        rate = 12_000.0 if report < 4 else controller.sending_bps  # patches after 1 s
        allowed.append(rate)
        size = round(rate * 0.25 / 8 / 5) - IP_UDP_BYTES  # 5 datagrams a report
        for _ in range(5):
            controller.on_sent(index, t)
            index, t = index + 1, t + 0.05
        got, nbytes = got + 5, nbytes + 5 * size
        controller.on_report(t + 0.01, index - 1, round((t + 0.05) * 1000), got, nbytes)
    assert allowed[4] == pytest.approx(1.2 * 12_000 + 4_000, rel=0.02)
    reached = next(i for i, a in enumerate(allowed) if a >= 0.95 * 64_000)
    assert 4 + 4 <= reached <= 4 + 6  # a fifth and 4 kbit/s a report: 6 reports, 1.5 s


def test_not_raised_past_what_was_received() -> None:
    """A sender with little to send does not claim a link it never tried."""
    controller = RateController(start_bps=64_000)  # above 1.5 x 24 + 10
    simulate(controller, 20)
    assert controller.rate_bps == 64_000


def test_growing_queue_brings_the_rate_down() -> None:
    controller = RateController(start_bps=64_000)
    steps = simulate(controller, 12, delay=growing_queue(since=4))
    first = next(i for i, s in enumerate(steps) if s.queue_ms > QUEUE_HIGH_MS)
    assert all(s.decreases == 0 for s in steps[:first])
    cut = steps[first]
    assert cut.decreases == 1
    assert cut.rate_bps == pytest.approx(DECREASE * cut.received_bps)
    # The queue grows by 0.1 s a second: the receiver gets 1/1.1 of what is sent.
    assert cut.received_bps == pytest.approx(RECEIVED_BPS / 1.1, rel=0.05)
    assert steps[-1].rate_bps == pytest.approx(0.85 * RECEIVED_BPS / 1.1, rel=0.05)
    assert steps[-1].queue_ms > 700


@pytest.mark.parametrize("phase", [0, 1])
def test_a_cut_follows_what_the_receiver_got_over_a_second(phase: int) -> None:
    """The receiver stamps datagrams when its loop reads them: a loop busy drawing a frame
    reads some 100 ms late, so one report's span between newest arrivals reads short and its
    rate high (here every other interval: 1.7 times the link's). Over a second of reports the
    cut still lands under what the link carries."""
    controller = RateController()

    def read_late(t: float) -> float:
        late = 0.1 if int((t - T0) / 0.25) % 2 == phase else 0.0
        return 0.05 + late + max(0.0, t - T0 - 2) * 0.1

    steps = simulate(controller, 4, delay=read_late)
    cut = next(s for s in steps if s.decreases)
    assert cut.rate_bps <= 0.85 * RECEIVED_BPS * 1.1


def test_queue_under_the_high_mark_holds_the_rate() -> None:
    """30 ms of queue, between 20 and 40: neither up nor down."""
    controller = RateController()
    steps = simulate(controller, 10, delay=lambda t: 0.05 if t < T0 + 3 else 0.08)
    held = [s for s in steps if s.now > T0 + 3.5]
    assert all(s.queue_ms == pytest.approx(30, abs=2) for s in held)
    assert {s.rate_bps for s in held} == {held[0].rate_bps}
    assert controller.decreases == 0


def test_loss_with_a_queue_brings_the_rate_down() -> None:
    """A full queue drops: loss and 30 ms of queue (under the delay's own mark) cut the rate."""
    controller = RateController()
    steps = simulate(controller, 5, lost=every_fifth, delay=lambda t: 0.05 if t < T0 + 1 else 0.08)
    assert steps[-1].loss == pytest.approx(0.2, abs=0.01)
    assert controller.decreases >= 1
    assert controller.rate_bps <= 0.85 * 0.8 * RECEIVED_BPS * 1.05


def test_loss_without_a_queue_is_the_links_own() -> None:
    """Random loss on a link with no queue (a radio link): sending less would not cure it."""
    controller = RateController()
    steps = simulate(controller, 5, lost=every_fifth)
    assert steps[-1].loss == pytest.approx(0.2, abs=0.01)
    assert controller.decreases == 0


def test_repeats_run_from_the_start_until_the_reports_show_no_loss() -> None:
    """The updates are repeated from a call's start (a loss before the first report would
    freeze the picture), stop after some seconds of clean reports, and start again with loss;
    only loss the reports show makes the datagrams carry fewer frames (``losing``)."""
    controller = RateController()
    assert controller.lossy and not controller.losing
    steps: list[tuple[float, bool, bool]] = []

    def watch(c: RateController, now: float) -> None:
        steps.append((now - T0, c.lossy, c.losing))

    simulate(controller, 12, lost=lambda n: n >= 160 and n % 5 == 2, extra=watch)
    clean = [t for t, lossy, _ in steps if not lossy]
    assert clean and 2.0 < clean[0] < 8.0  # some seconds of reports without loss
    assert not any(losing for t, _, losing in steps if t < 8.0)
    assert steps[-1][1:] == (True, True)  # loss from 8 s on: repeats again, and fewer frames


@pytest.mark.parametrize(
    ("seconds", "lost_early", "losing_at_start", "losing_after"),
    [
        (0.1, False, True, False),  # a fast join: assumed, until clean reports say otherwise
        (0.1, True, True, True),  # a fast join whose first reports show loss: it stays
        (0.2, False, True, False),  # a 40 ms link's join, its round trips counted
        (0.4, False, False, False),  # a 48 kbit/s link's
        (0.8, False, False, False),  # a thin link's join (24 kbit/s): headers cost too much
    ],
)
def test_a_fast_join_starts_losing_until_its_reports_show_none(
    seconds: float, lost_early: bool, losing_at_start: bool, losing_after: bool
) -> None:
    """One frame a datagram and the second-level repeats from a fast join on: at 5% loss,
    datagrams lost before any report said so froze the picture. The path opens before the
    snapshot is in, so a report or two (of heartbeats) come before the join. It ends after
    CLEAN_START_DATAGRAMS reported arrived, not after some seconds: the first reports come
    while the receiver builds its decoder, of a heartbeat or two."""
    controller = RateController()
    steps: list[tuple[float, bool]] = []

    def join_at_the_third_report(c: RateController, now: float) -> None:
        if len(steps) == 2:
            c.on_join(2300 * 8, seconds)
        steps.append((now - T0, c.losing))

    simulate(
        controller,
        6,
        lost=(lambda n: n in (13, 19)) if lost_early else (lambda n: False),
        extra=join_at_the_third_report,
    )
    joined = steps[2][0]
    clean_s = CLEAN_START_DATAGRAMS / FPS  # 2.25 s of datagrams at 20 a second
    assert not any(losing for t, losing in steps if t < joined)
    assert all(losing == losing_at_start for t, losing in steps[3:] if t < joined + 2.0)
    later = [losing for t, losing in steps if t > joined + clean_s + 0.6]
    assert later and all(losing == losing_after for losing in later)


@pytest.mark.parametrize("report_every", [0.25, 0.5])
def test_the_repeats_stop_after_as_many_seconds_whatever_the_reports_beat(
    report_every: float,
) -> None:
    """The loss average weighs each report by the time it covers: reports at half the beat
    stop the repeats of a clean call's start as soon (counted per report, at 0.5 s they ran
    twice as long, doubling the frames' bytes for 5 s more)."""
    controller = RateController()
    stopped: list[float] = []

    def watch(c: RateController, now: float) -> None:
        if not c.lossy and not stopped:
            stopped.append(now - T0)

    simulate(controller, 12, report_every=report_every, extra=watch)
    assert stopped and 4.0 < stopped[0] < 6.5, stopped


def test_reports_are_wanted_at_the_faster_beat_only_while_there_is_something_to_follow() -> None:
    """At the start (the repeats run), with a queue, and for a while after a cut: yes; on a
    clean, steady link: no (it halves what the reports cost)."""
    controller = RateController()
    wanted: list[tuple[float, bool]] = []

    def watch(c: RateController, now: float) -> None:
        wanted.append((now - T0, c.wants_reports(now)))

    simulate(controller, 16, delay=growing_queue(since=10, per_s=0.2), extra=watch)
    assert wanted[0][1]  # the start
    assert not any(w for t, w in wanted if 7.0 < t < 10.0)  # clean and steady
    assert all(w for t, w in wanted if t > 10.5)  # the queue grows (and the cuts follow)
    assert controller.decreases


def test_at_most_one_decrease_per_hold() -> None:
    controller = RateController()
    steps = simulate(controller, 8, delay=growing_queue(since=1), report_every=0.0625)
    cuts = [
        s.now for prev, s in zip(steps, steps[1:], strict=False) if s.decreases > prev.decreases
    ]
    assert steps[0].decreases == 0
    assert len(cuts) >= 8  # the queue stays high: a cut every hold
    gaps = [b - a for a, b in zip(cuts, cuts[1:], strict=False)]
    assert min(gaps) >= DECREASE_HOLD_S - 1e-9
    assert max(gaps) < DECREASE_HOLD_S + 0.0625 + 1e-9


def test_never_below_the_minimum() -> None:
    controller = RateController()
    simulate(controller, 10, lost=lambda n: n % 50 != 0, delay=growing_queue(since=0))  # 98% lost
    assert controller.decreases >= 1
    assert controller.rate_bps == MIN_RATE_BPS


def test_reports_of_unknown_datagrams_change_nothing() -> None:
    """A report naming a datagram the sender does not remember (never sent, or forgotten)."""

    def unknown(controller: RateController, now: float) -> None:
        for highest in (12, 69_999, 2**32 - 1, 10_000_000):
            controller.on_report(now, highest, 5, 10**6, 10**9)

    for scenario in SCENARIOS:
        plain = simulate(RateController(start_bps=20_000), 8, **scenario)
        noisy = simulate(RateController(start_bps=20_000), 8, extra=unknown, **scenario)
        assert noisy == plain


def test_unknown_report_alone_changes_nothing() -> None:
    controller = RateController()
    controller.on_sent(5, 1.0)
    controller.on_report(1.1, 6, 1050, 1, 100)
    assert controller.rate_bps == START_RATE_BPS
    assert controller.last == RateController().last
    assert controller.decreases == 0


@pytest.mark.parametrize("offset_s", [1e6, -50.0, 4e6])
def test_clock_offset_between_the_ends_changes_nothing(offset_s: float) -> None:
    """Only differences of one-way delays count: the clocks' offset cancels."""
    for scenario in SCENARIOS:
        base = simulate(RateController(start_bps=20_000), 10, **scenario)
        shifted = simulate(RateController(start_bps=20_000), 10, offset_s=offset_s, **scenario)
        assert [s.rate_bps for s in shifted] == pytest.approx([s.rate_bps for s in base])
        assert [s.decreases for s in shifted] == [s.decreases for s in base]
        assert [s.queue_ms for s in shifted] == pytest.approx([s.queue_ms for s in base], abs=1e-3)


def test_forgets_old_send_times() -> None:
    """Send times are kept for about 2048 datagrams; a report of an older one is ignored."""
    controller = RateController()
    for i in range(3000):
        controller.on_sent(i, i / 30)
    controller.on_report(100.0, 10, 1000, 1, 100)  # forgotten
    assert controller.last == RateController().last
    controller.on_report(100.0, 2999, 100_050, 1, 100)  # remembered
    assert controller.last.queue_ms == 0.0


def test_a_queue_in_the_first_second_cuts_from_the_estimate() -> None:
    """The call's first reports cover a few datagrams: what got through says little of what
    the link carries. A queue then (the snapshot's draft still crossing on TCP) cut the rate
    to its floor from those few (6 kbit/s), and it crawled back at 8% a second: the full
    snapshot took 20 s at 24 kbit/s."""
    controller = RateController()
    for index, at in enumerate((T0, T0 + 0.2, T0 + 0.4)):
        controller.on_sent(index, at)
    controller.on_report(T0 + 0.1, 0, round((T0 + 0.05) * 1000), 1, SIZE)
    # The third datagram came 100 ms behind the first one's delay: a queue.
    controller.on_report(T0 + 0.6, 2, round((T0 + 0.55) * 1000), 3, 3 * SIZE)
    assert controller.last.queue_ms == pytest.approx(100, abs=1)
    assert controller.last.received_bps < MIN_RATE_BPS  # a few datagrams over half a second
    assert controller.decreases == 1
    assert controller.rate_bps == pytest.approx(DECREASE * START_RATE_BPS)
