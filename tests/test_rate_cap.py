"""The geometry's rate cap (sender/rate_cap.py): the bucket, and a call held under it."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.loopback import Loopback
from facewire.protocol.packets import KeyFrame
from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path
from facewire.sender.encoder import FaceEncoder
from facewire.sender.rate_cap import EDGE_KBPS, LOW_S, SLACK_STEPS, START_S, RateCap

FPS = 30.0


def test_the_bucket_fills_by_the_frame_and_lets_debt_be_paid_back() -> None:
    cap = RateCap(1.2, FPS, bucket_s=1.0)  # 150 bytes a second, 5 a frame
    assert cap.tokens == pytest.approx(150 * START_S)
    assert cap.next_frame() and cap.tokens == pytest.approx(150 * START_S + 5)
    cap.spend(100)  # a keyframe: into debt
    waits = 0
    while not cap.next_frame():
        waits += 1
    assert waits == int(np.ceil((100 - 150 * START_S - 5) / 5)) - 1
    for _ in range(100):
        cap.next_frame()
    assert cap.tokens == pytest.approx(150.0)  # never more than the bucket
    with pytest.raises(ValueError, match="must be > 0"):
        RateCap(0.0, FPS)


def test_the_quantiser_loosens_as_the_bucket_runs_low() -> None:
    cap = RateCap(1.2, FPS, bucket_s=1.0)  # 150 bytes a second
    low = 150 * LOW_S
    for tokens, slack in ((150.0, 0.0), (low, 0.0), (low / 2, SLACK_STEPS / 2), (0.0, SLACK_STEPS)):
        cap.tokens = tokens
        assert cap.slack() == pytest.approx(slack)
    cap.tokens = -100.0  # in debt after a keyframe
    assert cap.slack() == pytest.approx(SLACK_STEPS)


def _call(
    frames: list[CapturedFrame], kbps: float | None, slack_steps: float | None = None
) -> tuple[FaceEncoder, int, int]:
    """Both ends over ``frames`` (packets as bytes); after every frame the sender's idea of
    what the receiver holds is what the receiver decoded. Returns the encoder, the frame
    packets' bytes and the keyframes. ``slack_steps``: the cap's, if not its own."""
    encoder = FaceEncoder(640, 480, FPS, rem=False, refresh=False, geometry_kbps=kbps)
    if slack_steps is not None:
        assert encoder.rate_cap is not None
        encoder.rate_cap.slack_steps = slack_steps
    nbytes = keyframes = 0
    with Loopback(encoder, frames[0]) as both:
        for frame in frames[1:]:
            sent = both.send(frame)
            nbytes += sum(len(data) for data in sent)
            keyframes += sum(isinstance(p, KeyFrame) for p in both.receive(sent))
            shown = both.shown
            assert shown is not None and encoder.values is not None
            for name, value in encoder.values.items():
                assert np.array_equal(shown.values[name], value), (frame.index, name)
    return encoder, nbytes, keyframes


@pytest.fixture(scope="module")
def clip() -> list[CapturedFrame]:
    """The bundled clip's first 5 s."""
    with VideoSource(demo_clip_path()) as video:
        return [
            CapturedFrame(f.index, f.image, round(f.index * 1e6 / FPS))
            for f in video.frames(limit=150)
        ]


def test_a_call_over_its_cap_holds_frames_and_keeps_to_it(clip: list[CapturedFrame]) -> None:
    """The bundled clip's first 5 s cost about 1.4 kbit/s; capped at 0.6 the sender holds
    frames back, keeps to the cap (plus the bucket's start), still sends the periodic
    keyframe, and the receiver always holds what the sender thinks it holds."""
    seconds = (len(clip) - 1) / FPS
    free, free_bytes, _ = _call(clip, None)
    assert free.rate_cap is None and free_bytes * 8 / seconds / 1000 > 1.0
    capped, nbytes, keyframes = _call(clip, 0.6)
    assert capped.rate_cap is not None and capped.rate_cap.held > 20
    assert keyframes == 2  # the first, and the periodic one at 4 s
    start = 0.6 * 1000 / 8 * START_S
    # The face's edge corrections and the body's motion ride in the same packets, each on a
    # bucket of its own.
    face = nbytes - capped.edge_bytes - capped.body_bytes
    assert face <= 0.6 * 1000 / 8 * seconds + start + 60  # the keyframe's debt at most
    edge = EDGE_KBPS * 1000 / 8
    assert 0 < capped.edge_bytes <= edge * (seconds + START_S) + 20  # a packet's share of debt


def test_a_loosened_quantiser_holds_back_fewer_frames(clip: list[CapturedFrame]) -> None:
    """Under the same cap, the hysteresis that widens as the bucket runs low sends coarser
    changes instead of holding whole frames back: the face stops dead less often."""
    loose, _, _ = _call(clip, 0.6)
    strict, _, _ = _call(clip, 0.6, slack_steps=0.0)
    assert loose.rate_cap is not None and strict.rate_cap is not None
    assert loose.rate_cap.held < 0.8 * strict.rate_cap.held


def test_a_new_rate_keeps_the_bucket_and_its_count() -> None:
    """The pictures' buckets follow the link (RateCap.set_rate): what the bucket holds is
    kept up to its new depth, and the frames held back stay counted."""
    cap = RateCap(1.5, 30.0)
    cap.tokens, cap.held = cap.capacity, 3
    cap.set_rate(0.75)
    assert cap.capacity == pytest.approx(0.75 * 1000 / 8 * cap.bucket_s)
    assert cap.tokens == cap.capacity and cap.held == 3
    cap.set_rate(0.0)
    assert cap.tokens == 0.0 and not cap.next_frame() and cap.slack() == cap.slack_steps
