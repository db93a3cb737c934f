"""The sender's channel filters: jitter removed, motion followed, in units of steps; and the
encoder with them on the bundled clip (fewer bits, the quantisation budget still held)."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.models.face_channels import HYSTERESIS, POSE_ROTATION, POSE_TRANSLATION, WIRE
from facewire.sender.channel_filter import MAX_GAP_S, ChannelSmoother

FPS = 30.0
STEPS = {POSE_ROTATION: 0.005, WIRE: 0.05}


def run(smoother: ChannelSmoother, name: str, xs: np.ndarray) -> np.ndarray:
    """Filter a (T, k) sequence of one channel, in steps, at 30 fps."""
    step = smoother.steps[name]
    return np.array([smoother({name: x * step}, i / FPS)[name] / step for i, x in enumerate(xs)])


@pytest.mark.parametrize("name", [POSE_ROTATION, WIRE])
def test_a_still_value_passes_unchanged(name: str) -> None:
    xs = np.tile([3.0, -7.0, 0.25], (40, 1))
    assert np.allclose(run(ChannelSmoother(STEPS), name, xs), xs)


@pytest.mark.parametrize("name", [POSE_ROTATION, WIRE])
def test_jitter_is_removed(name: str) -> None:
    rng = np.random.default_rng(1)
    xs = 10.0 + rng.normal(0.0, 0.5, (300, 3))  # half a step RMS of tracker jitter
    out = run(ChannelSmoother(STEPS), name, xs)
    # A third of it goes; more would take the lag that shows on real motion.
    assert out[30:].std() < 0.75 * xs[30:].std()
    assert abs(out[30:].mean() - 10.0) < 0.2


def test_a_sudden_expression_is_followed_within_a_few_frames() -> None:
    # A blink: 20 steps in one frame, held for 5 frames. The filter opens with the speed.
    xs = np.zeros((30, 1))
    xs[10:15] = 20.0
    out = run(ChannelSmoother(STEPS), WIRE, xs)[:, 0]
    assert out[11] > 10.0 and out[12] > 16.0
    assert out[16] < 5.0  # and lets go again


def test_steady_head_motion_is_followed_with_little_lag() -> None:
    xs = np.arange(60)[:, None] * np.array([[2.0, -1.0, 0.5]])  # steps per frame
    out = run(ChannelSmoother(STEPS), POSE_ROTATION, xs)
    assert np.abs(out[20:] - xs[20:]).max() < 1.0


def test_filtering_is_in_steps() -> None:
    # The same motion in other units (another step) is filtered the same way.
    rng = np.random.default_rng(2)
    xs = np.cumsum(rng.normal(0, 1, (50, 2)), axis=0)
    a = run(ChannelSmoother({WIRE: 0.05}), WIRE, xs)
    b = run(ChannelSmoother({WIRE: 3.0}), WIRE, xs)
    assert np.allclose(a, b)


def test_a_pause_restarts_the_filter() -> None:
    s = ChannelSmoother(STEPS)
    s({WIRE: np.zeros(2)}, 0.0)
    s({WIRE: np.zeros(2)}, 1 / FPS)
    # The face was lost for longer than MAX_GAP_S: the new value is taken as it is.
    out = s({WIRE: np.full(2, 1.0)}, 1 / FPS + MAX_GAP_S + 0.1)
    assert np.allclose(out[WIRE], 1.0)
    s.reset()
    assert np.allclose(s({WIRE: np.full(2, -1.0)}, 5.0)[WIRE], -1.0)


def test_unfiltered_channels_pass_through() -> None:
    s = ChannelSmoother({WIRE: 0.05, "lips": 0.1}, settings={"lips": None})
    s({WIRE: np.zeros(1), "lips": np.zeros(1), "extra": np.zeros(1)}, 0.0)
    out = s({WIRE: np.ones(1), "lips": np.ones(1), "extra": np.ones(1)}, 1 / FPS)
    assert out["lips"][0] == 1.0 and out["extra"][0] == 1.0 and out[WIRE][0] < 1.0


def test_bad_steps_are_refused() -> None:
    with pytest.raises(ValueError, match="channel 'wire': step must be finite and > 0"):
        ChannelSmoother({WIRE: 0.0})


def _encode(frames: list, smoothing: bool) -> tuple[int, list[float], list[float]]:
    """Bytes sent, and per frame the largest quantisation error (in steps) against what the
    sender meant and the sent translation z."""
    from facewire.protocol.quant import dequantise
    from facewire.sender.encoder import FaceEncoder

    h, w = frames[0].image.shape[:2]
    # No rate caps: they would hold the unsmoothed call's values back and hide what it costs.
    encoder = FaceEncoder(
        w,
        h,
        FPS,
        session_id=1,
        smoothing=smoothing,
        geometry_kbps=None,
        edge_kbps=None,
        body_kbps=None,
    )
    snapshot = encoder.start(frames[0])
    assert snapshot is not None
    table = {name: step for name, _, step in snapshot.channels}
    sent, errors, depth = 0, [], []
    for f in frames[1:]:
        packet = encoder.encode(f)
        sent += 0 if packet is None else len(bytes(packet))
        assert encoder.intended is not None and encoder._channels is not None
        shown = encoder._channels.last
        assert shown is not None
        errors.append(
            max(
                float(np.abs(dequantise(shown.values[n], s) - encoder.intended[n]).max() / s)
                for n, s in table.items()
            )
        )
        depth.append(float(shown.values[POSE_TRANSLATION][2]))
    return sent, errors, depth


def test_the_encoder_sends_less_and_keeps_the_budget() -> None:
    from facewire.sender.capture import VideoSource, demo_clip_path

    with VideoSource(demo_clip_path()) as video:
        frames = list(video.frames(limit=90))  # still, then head motion and a smile
    smooth_bytes, errors, depth = _encode(frames, smoothing=True)
    raw_bytes, _, _ = _encode(frames, smoothing=False)
    assert smooth_bytes < 0.85 * raw_bytes
    # The receiver gets what the sender meant to within the hysteresis quantiser's bound.
    assert max(errors) <= 0.5 + HYSTERESIS + 1e-9
    # The head's depth is invisible on screen: it never changes.
    assert len(set(depth)) == 1
