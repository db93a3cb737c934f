"""The playout's schedule, on a simulated clock: frames that arrive unevenly are shown evenly
in capture order, the screen holds (never guesses) when a frame is late or lost, and nothing
is blended across lost frames. The receive loop is driven as run_receiver drives it: push what
has arrived, poll, wait as long as the playout says. Real calls: tests/test_playout_call.py.
"""

from __future__ import annotations

import random
from collections.abc import Iterable

import numpy as np
import pytest

from facewire.protocol.channels import FrameValues
from facewire.receiver.playout import (
    AUTO_MAX_US,
    AUTO_START_US,
    MAX_SLEW,
    ArrivalPlayout,
    JitterBuffer,
    Playout,
    PlayoutSettings,
    Record,
    Show,
    make_playout,
)
from facewire.receiver.smoothness import display_figures

FRAME_US = 33_333
START_US = 5_000_000  # sender clock of frame 0
OFFSET_US = 1_000_000_000  # receiver clock - sender clock (two hosts, no common clock)
END_US = OFFSET_US + START_US + 20_000_000  # after every call here


def frame(seq: int, capture_us: int | None = None) -> FrameValues:
    capture = START_US + seq * FRAME_US if capture_us is None else capture_us
    return FrameValues(seq, capture, {"x": np.array([seq], np.int64)})


def play(
    playout: Playout,
    arrivals: Iterable[tuple[int, FrameValues, bool]],
    until_us: int,
) -> list[tuple[int, Record | Show]]:
    """Drive ``playout`` like the receive loop: (arrival on the receiver's clock, frame,
    after a gap) in arrival order; returns (receiver time, step) of every step."""
    pending = sorted(arrivals, key=lambda a: a[0])
    now = min(a[0] for a in pending)
    out: list[tuple[int, Record | Show]] = []
    while now <= until_us:
        while pending and pending[0][0] <= now:
            _, values, gap = pending.pop(0)
            playout.push(values, now, gap)
        out += [(now, step) for step in playout.poll(now)]
        wake = now + max(1, playout.wait_us(now))
        now = min(wake, pending[0][0]) if pending else wake
    return out


def shows(steps: list[tuple[int, Record | Show]]) -> list[tuple[int, Show]]:
    return [(t, s) for t, s in steps if isinstance(s, Show)]


def jittered(n: int, jitter_us: int, seed: int = 1) -> list[tuple[int, FrameValues, bool]]:
    """Frames 0..n-1 on a path of 40 ms +- jitter_us, in order (TCP: a frame waits for the
    ones before it); frame 0 takes the fastest path."""
    rng = random.Random(seed)
    out, last = [], 0
    for seq in range(n):
        values = frame(seq)
        spread = 0 if seq == 0 else rng.randint(0, 2 * jitter_us)
        arrival = max(last, OFFSET_US + values.capture_us + 40_000 - jitter_us + spread)
        out.append((arrival, values, False))
        last = arrival
    return out


def test_frames_that_arrive_unevenly_are_shown_evenly_in_capture_order() -> None:
    arrivals = jittered(90, 15_000)
    arrival_gaps = np.diff([a for a, _, _ in arrivals]) / 1000
    assert arrival_gaps.std() > 8  # the network's jitter: 33 ms +- up to 30
    buffer = JitterBuffer(40_000, FRAME_US, FRAME_US)
    steps = play(buffer, arrivals, arrivals[-1][0] + 200_000)
    shown = shows(steps)
    # Every frame once, as it is, in capture order.
    assert [s.a.seq for _, s in shown] == list(range(90))
    assert all(s.b is None and s.media_us == s.a.capture_us for _, s in shown)
    # At even intervals: the display rate, give or take the clock's slew.
    gaps = np.diff([t for t, _ in shown])
    assert np.all(np.abs(gaps - FRAME_US) <= FRAME_US * MAX_SLEW + 2), gaps
    # The recording: every frame's own picture, in order.
    records = [s for _, s in steps if isinstance(s, Record)]
    assert [(r.seq, r.values is not None) for r in records] == [(i, True) for i in range(90)]
    # Nothing is shown before it is due: the fastest path plus the delay.
    for t, s in shown:
        assert t - s.media_us >= OFFSET_US + 25_000 + 40_000


def test_on_arrival_the_same_frames_show_the_jitter() -> None:
    arrivals = jittered(90, 15_000)
    shown = shows(play(ArrivalPlayout(), arrivals, arrivals[-1][0] + 200_000))
    gaps = np.diff([t for t, _ in shown]) / 1000
    assert gaps.std() > 8
    figures = display_figures([(t, s.media_us) for t, s in shown], FRAME_US)
    buffered = shows(play(JitterBuffer(40_000, FRAME_US, FRAME_US), arrivals, END_US))
    even = display_figures([(t, s.media_us) for t, s in buffered], FRAME_US)
    assert figures["motion_jitter_ms"] > 8 > 1 > even["motion_jitter_ms"]
    assert figures["repeated"] + figures["skipped"] > 10
    assert even["repeated"] == even["skipped"] == 0


def test_a_late_frame_holds_the_picture_and_the_picture_catches_up() -> None:
    arrivals = jittered(30, 0)
    late = 12
    arrivals[late] = (arrivals[late][0] + 80_000, arrivals[late][1], False)  # 80 ms late
    for i in range(late + 1, 30):  # TCP: the frames behind it wait
        arrivals[i] = (max(arrivals[i][0], arrivals[late][0]), arrivals[i][1], False)
    steps = play(JitterBuffer(20_000, FRAME_US, FRAME_US), arrivals, END_US)
    shown = shows(steps)
    seqs = [s.a.seq for _, s in shown]
    # Nothing is guessed: no picture after frame 11 until the late frames are there.
    assert all(s.b is None for _, s in shown)
    after = seqs.index(late - 1) + 1
    assert shown[after][0] - shown[after - 1][0] >= 80_000
    assert shown[after][0] >= arrivals[late][0]
    # Then it catches up: frames more than a tick overdue are dropped (held in the
    # recording), and the last ones are shown on time again.
    assert seqs == sorted(seqs) and late not in seqs
    records = {s.seq: s.values is not None for _, s in steps if isinstance(s, Record)}
    assert list(records) == list(range(30))
    assert [seq for seq, own in records.items() if not own] == [
        s for s in range(30) if s not in seqs
    ]
    assert seqs[-3:] == [27, 28, 29]
    assert shown[-1][0] - shown[-1][1].media_us < OFFSET_US + 25_000 + 20_000 + FRAME_US


def test_nothing_is_blended_across_lost_frames() -> None:
    arrivals = [a for a in jittered(40, 5_000) if not 10 <= a[1].seq < 20]
    keyframe = next(i for i, a in enumerate(arrivals) if a[1].seq == 20)
    arrivals[keyframe] = (*arrivals[keyframe][:2], True)  # the chain broke before it
    steps = play(JitterBuffer(40_000, FRAME_US // 2, FRAME_US), arrivals, END_US)
    shown = shows(steps)
    # At twice the sender's rate every other picture lies between two frames, except
    # across the gap: frame 9 holds until frame 20 is due.
    assert any(s.b is not None for _, s in shown)
    assert not [s for _, s in shown if s.b is not None and s.a.seq == 9]
    i9 = [s.a.seq for _, s in shown].index(9)
    assert shown[i9 + 1][1].a.seq == 20 and shown[i9 + 1][1].b is None
    assert shown[i9 + 1][0] - shown[i9][0] >= 10 * FRAME_US
    records = [s for _, s in steps if isinstance(s, Record)]
    assert [r.seq for r in records] == [*range(10), *range(20, 40)]
    assert [r.seq for r in records if r.after_gap] == [20]


def test_between_two_frames_at_twice_the_rate() -> None:
    arrivals = jittered(20, 10_000)
    steps = play(JitterBuffer(40_000, FRAME_US // 2, FRAME_US), arrivals, END_US)
    shown = [s for _, s in shows(steps)]
    exact = [s.a.seq for s in shown if s.b is None]
    between = [(s.a.seq, s.b.seq, round(s.t, 2)) for s in shown if s.b is not None]
    assert exact == list(range(20))
    assert between == [(i, i + 1, 0.5) for i in range(19)]
    media = [s.media_us for s in shown]
    assert media == sorted(media) and len(set(media)) == len(media)
    # The recording is the sender's frames, once each: pictures between are not in it.
    assert [s.seq for _, s in steps if isinstance(s, Record)] == list(range(20))


def test_between_two_frames_at_three_times_the_rate() -> None:
    """Each picture between two frames shows its own instant: a third and two thirds of the way
    (at twice the rate, 0.5 is right whatever t the playout computes)."""
    arrivals = jittered(20, 10_000)
    steps = play(JitterBuffer(40_000, FRAME_US / 3, FRAME_US), arrivals, END_US)
    between = [s for _, s in shows(steps) if s.b is not None]
    ts = [round(s.t, 2) for s in between]
    assert set(ts) == {0.33, 0.67} and ts.count(0.33) >= 15 and ts.count(0.67) >= 15, ts
    for s in between:  # the instant it shows is where t puts it
        assert s.b is not None and s.b.seq == s.a.seq + 1
        assert s.media_us - s.a.capture_us == pytest.approx(s.t * FRAME_US, abs=1)


def test_a_still_face_holds_until_the_frame_before_the_next() -> None:
    # Frames 5..9 sent no packet (nothing changed): frame 4's values stand until frame 9.
    arrivals = [a for a in jittered(20, 0) if not 5 <= a[1].seq <= 9]
    shown = [
        s for _, s in shows(play(JitterBuffer(40_000, FRAME_US // 2, FRAME_US), arrivals, END_US))
    ]
    after4 = [(s.b and s.b.seq, s.media_us) for s in shown if s.a.seq == 4]
    # Shown as it is, then only the last half frame before frame 10 moves towards it.
    assert after4 == [(None, START_US + 4 * FRAME_US), (10, START_US + 19 * (FRAME_US // 2))]


def test_frames_stamped_late_are_shown_at_their_frame_times() -> None:
    # A sender that fell behind stamps the frames it catches up on late: frame 6 25 ms late,
    # frame 7 10 ms, 18 ms apart.
    arrivals = jittered(16, 0)
    for seq, lag in ((6, 25_000), (7, 10_000)):
        values = frame(seq, START_US + seq * FRAME_US + lag)
        arrivals[seq] = (OFFSET_US + values.capture_us + 25_000, values, False)
    shown = shows(play(JitterBuffer(40_000, FRAME_US, FRAME_US), arrivals, END_US))
    assert [s.a.seq for _, s in shown] == list(range(16))
    assert all(s.b is None for _, s in shown)
    assert [s.media_us for _, s in shown] == [START_US + i * FRAME_US for i in range(16)]
    assert np.all(np.abs(np.diff([t for t, _ in shown]) - FRAME_US) <= FRAME_US * MAX_SLEW)


def test_the_adaptive_delay_follows_the_jitter() -> None:
    calm, rough = JitterBuffer(None, FRAME_US, FRAME_US), JitterBuffer(None, FRAME_US, FRAME_US)
    assert calm.delay_us == AUTO_START_US  # until it has seen the network
    play(calm, jittered(300, 1_000), END_US)
    play(rough, jittered(300, 20_000), END_US)
    assert calm.delay_us < 10_000
    assert 35_000 < rough.delay_us < 45_000  # the 95th percentile of 0..40 ms, plus a margin
    stormy = JitterBuffer(None, FRAME_US, FRAME_US)
    play(stormy, jittered(300, 100_000), END_US)
    assert stormy.delay_us == AUTO_MAX_US  # no more than that, whatever the network does


def test_frames_read_late_by_a_busy_loop_do_not_widen_the_delay() -> None:
    # Every third frame waited in the socket while a picture was drawn: its arrival time
    # is when the loop got to it, 30 ms after it came. It says nothing of the network.
    arrivals = jittered(300, 1_000)
    busy = JitterBuffer(None, FRAME_US, FRAME_US)
    for i, (arrival, values, gap) in enumerate(arrivals):
        late = i % 3 == 1
        busy.push(values, arrival + (30_000 if late else 0), gap, timed=not late)
    assert busy.delay_us < 10_000


def test_a_sender_clock_that_steps_back_is_followed() -> None:
    arrivals = jittered(200, 2_000)
    # From frame 100 on the sender's clock reads 30 s less (its machine set its clock).
    arrivals = [
        (a, frame(v.seq, v.capture_us - 30_000_000) if v.seq >= 100 else v, g)
        for a, v, g in arrivals
    ]
    buffer = JitterBuffer(40_000, FRAME_US, FRAME_US)
    shown = shows(play(buffer, arrivals, END_US))
    last = shown[-1]
    assert last[1].a.seq == 199
    # Back to the fastest path plus the delay, not 30 s behind.
    assert last[0] - arrivals[-1][0] < 200_000


def test_on_arrival_the_newest_is_drawn_and_the_ones_it_overtook_are_held() -> None:
    playout = ArrivalPlayout()
    for seq in range(3):
        playout.push(frame(seq), OFFSET_US + seq, after_gap=seq == 1)
    steps = playout.poll(OFFSET_US + 10)
    assert [(type(s).__name__, getattr(s, "seq", None)) for s in steps] == [
        ("Record", 0),
        ("Record", 1),
        ("Record", 2),
        ("Show", None),
    ]
    assert [s.values is None for s in steps[:3]] == [True, True, False]  # type: ignore[union-attr]
    assert steps[1].after_gap  # type: ignore[union-attr]
    assert playout.poll(OFFSET_US + 20) == []


def test_on_arrival_the_frames_of_one_datagram_are_drawn_at_their_own_pace() -> None:
    """A datagram carrying two frames (the sender's default): both drawn, 33 ms apart, from
    the first one's arrival on, so the screen keeps 30 pictures a second."""
    arrivals = []
    for pair in range(5):
        at = OFFSET_US + START_US + (2 * pair + 1) * FRAME_US + 5_000  # after its second frame
        arrivals += [(at, frame(2 * pair), False), (at, frame(2 * pair + 1), False)]
    steps = play(ArrivalPlayout(), arrivals, arrivals[-1][0] + 200_000)
    assert [s.seq for _, s in steps if isinstance(s, Record) and s.values is None] == []
    shown = shows(steps)
    assert [s.a.seq for _, s in shown] == list(range(10))
    gaps = np.diff([t for t, _ in shown])
    assert np.allclose(gaps, FRAME_US, atol=1)


def test_on_arrival_a_datagram_of_one_frame_among_pairs_keeps_the_pairs_pace() -> None:
    """Two frames a datagram, but frame 6 had nothing to send and frame 12 is a keyframe
    that left at once (13 then goes alone): their datagrams carry one frame, which came
    sooner after its capture than a pair's first. The pairs after them are still drawn both,
    33 ms apart (once, each pair for two seconds drew only its second frame: a quarter of
    the frames of a 1280x720 call were not drawn)."""
    arrivals = []
    for seq in range(40):
        if seq == 6:
            continue
        at = OFFSET_US + START_US + seq * FRAME_US + 5_000  # just after its capture
        if seq % 2 == 0 and seq != 12:
            at += FRAME_US  # the first of a pair waits for the second
        arrivals.append((at, frame(seq), False))
    steps = play(ArrivalPlayout(), arrivals, arrivals[-1][0] + 200_000)
    assert [s.seq for _, s in steps if isinstance(s, Record) and s.values is None] == []
    shown = shows(steps)
    assert [s.a.seq for _, s in shown] == [seq for seq in range(40) if seq != 6]
    # From the first pair on, every frame as late as the others: an even pace.
    late = [t - s.media_us for t, s in shown]
    assert max(late) - min(late) <= 1, late


def test_on_arrival_a_lost_datagrams_repeat_costs_a_picture_not_latency() -> None:
    """One datagram a frame; datagram 4 is lost and its frame comes again with frame 5 (the
    sender's repeat): frame 4 is not drawn, and frame 5 and those after it are drawn as soon
    as they come, not at frame 4's pace behind it."""
    arrivals = []
    for seq in range(10):
        if seq == 4:
            continue
        at = OFFSET_US + START_US + seq * FRAME_US + 5_000
        arrivals += [(at, frame(seq - 1), False)] if seq == 5 else []
        arrivals.append((at, frame(seq), False))
    steps = play(ArrivalPlayout(), arrivals, arrivals[-1][0] + 200_000)
    assert [s.seq for _, s in steps if isinstance(s, Record)] == list(range(10))
    shown = shows(steps)
    assert [s.a.seq for _, s in shown] == [0, 1, 2, 3, 5, 6, 7, 8, 9]
    for t, s in shown:
        assert t - s.media_us == shown[0][0] - shown[0][1].media_us  # all as late as the first


def test_on_arrival_frames_that_came_late_together_are_not_replayed() -> None:
    """After a stall, frames far apart that come in one read: the newest is drawn at once."""
    at = OFFSET_US + START_US + 10 * FRAME_US
    arrivals = [(at, frame(seq), False) for seq in range(10)]
    shown = shows(play(ArrivalPlayout(), arrivals, at + 500_000))
    assert [s.a.seq for _, s in shown][-1] == 9
    assert shown[-1][0] == at


def test_settings() -> None:
    assert isinstance(make_playout(PlayoutSettings(0), 30.0), ArrivalPlayout)
    buffer = make_playout(PlayoutSettings(80, 60), 25.0)
    assert isinstance(buffer, JitterBuffer)
    assert (buffer.delay_us, buffer.display_us, buffer.frame_us) == (80_000, 16_667, 40_000)
    with pytest.raises(ValueError, match="playout delay must be 0 to 2000 ms, got -1"):
        PlayoutSettings(-1)
    with pytest.raises(ValueError, match="display rate must be above 0"):
        PlayoutSettings(None, 0)


def test_display_figures() -> None:
    even = [(1_000_000 + i * 33_333, 5_000 + i * 33_333) for i in range(30)]
    figures = display_figures(even, 33_333)
    assert figures["repeated"] == figures["skipped"] == 0
    assert figures["motion_jitter_ms"] < 0.01 and abs(figures["interval_ms"]["p50"] - 33.3) < 0.1
    # Picture 10 comes 10 ms late: still in time for its refresh.
    late = list(even)
    late[10] = (late[10][0] + 10_000, late[10][1])
    assert display_figures(late, 33_333)["repeated"] == 0
    # 25 ms late: the screen shows picture 9 twice, and 11 replaces 10 before a refresh.
    late[10] = (late[10][0] + 15_000, late[10][1])
    figures = display_figures(late, 33_333)
    assert figures["repeated"] == 1 and figures["skipped"] == 1
    # Pictures 10 and 11 come together: 10 is replaced before a refresh shows it.
    bunched = list(even)
    bunched[10] = (bunched[11][0] - 1_000, bunched[10][1])
    figures = display_figures(bunched, 33_333)
    assert figures["repeated"] == 1 and figures["skipped"] == 1
