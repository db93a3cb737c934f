"""Quantisation to integers: error bounds, hysteresis, clipping, validation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from facewire.protocol.constants import MAX_CHANNEL_VALUE
from facewire.protocol.quant import dequantise, quantise

values = hnp.arrays(np.float64, st.integers(1, 20), elements=st.floats(-1e3, 1e3))


@given(values, st.floats(1e-3, 10.0))
def test_round_trip_error_at_most_half_a_step(x: np.ndarray, step: float) -> None:
    q, clipped = quantise(x, step)
    assert clipped == 0 and q.dtype == np.int64
    assert np.all(np.abs(dequantise(q, step) - x) <= step / 2 + 1e-9)


@given(values, values, st.floats(1e-3, 10.0), st.floats(0.0, 1.0))
def test_hysteresis_error_bound(x: np.ndarray, y: np.ndarray, step: float, h: float) -> None:
    y = np.resize(y, x.shape)
    prev, _ = quantise(y, step)
    q, _ = quantise(x, step, prev, h)
    assert np.all(np.abs(dequantise(q, step) - x) <= (0.5 + h) * step + 1e-9)


def test_hysteresis_holds_small_changes_and_follows_large_ones() -> None:
    prev = np.array([10, 10, 10])
    # 0.7 steps away: held with h = 0.25; 0.8 steps: moves; -1.2: moves to the nearest.
    q, _ = quantise(np.array([10.7, 10.8, 8.8]), 1.0, prev, 0.25)
    assert q.tolist() == [10, 11, 9]
    # Jitter of +-0.6 steps around a level never changes it.
    rng = np.random.default_rng(0)
    level = np.array([3])
    for _ in range(200):
        level, _ = quantise(3 + rng.uniform(-0.6, 0.6, 1), 1.0, level, 0.25)
        assert level.tolist() == [3]


def test_clipping_is_counted_and_symmetric() -> None:
    q, clipped = quantise(np.array([1e30, -1e30, 0.0]), 1.0)
    assert clipped == 2
    assert q.tolist() == [MAX_CHANNEL_VALUE, -MAX_CHANNEL_VALUE, 0]


def test_per_element_steps() -> None:
    q, _ = quantise(np.array([1.0, 1.0]), np.array([0.5, 0.25]))
    assert q.tolist() == [2, 4]
    assert dequantise(q, np.array([0.5, 0.25])).tolist() == [1.0, 1.0]


@pytest.mark.parametrize(
    ("x", "step", "message"),
    [
        ([float("nan")], 1.0, "cannot quantise non-finite values (1 of 1)"),
        ([1.0], 0.0, "quantisation steps must be finite and > 0"),
        ([1.0, 2.0], [1.0, 2.0, 3.0], "does not broadcast"),
    ],
)
def test_quantise_rejects(x: list[float], step: object, message: str) -> None:
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        quantise(np.array(x), step)  # type: ignore[arg-type]


def test_bad_hysteresis_and_previous() -> None:
    with pytest.raises(ValueError, match="hysteresis must be >= 0"):
        quantise(np.zeros(2), 1.0, np.zeros(2, np.int64), -0.1)
    with pytest.raises(ValueError, match=r"previous values of shape \(3,\), expected \(2,\)"):
        quantise(np.zeros(2), 1.0, np.zeros(3, np.int64), 0.25)


def test_dequantise_needs_integers() -> None:
    with pytest.raises(ValueError, match="expected an integer array"):
        dequantise(np.array([1.5]), 1.0)
