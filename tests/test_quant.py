"""Quantisation and pose helpers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from protocol.quant import (
    Pose,
    decode_pose,
    dequantise,
    encode_pose,
    quantise,
    quaternion_from_int16,
    quaternion_to_int16,
)

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


@given(hnp.arrays(np.float64, st.integers(0, 50), elements=finite), st.floats(0.05, 10.0))
def test_round_trip_error_at_most_half_a_step(values: np.ndarray, step: float) -> None:
    q, clipped = quantise(values, step)
    assert q.dtype == np.int16 and q.shape == values.shape
    assert clipped == 0
    assert np.all(np.abs(dequantise(q, step) - values) <= step / 2 + 1e-9)


def test_clipping_is_counted_and_symmetric() -> None:
    q, clipped = quantise([1e9, -1e9, 0.5, 3.0], 1.0)
    assert q.tolist() == [32767, -32767, 0, 3]
    assert clipped == 2


def test_per_element_steps() -> None:
    q, clipped = quantise([[1.0, 1.0], [2.0, 2.0]], [0.5, 0.25])
    assert q.tolist() == [[2, 4], [4, 8]]
    assert dequantise(q, [0.5, 0.25]).tolist() == [[1.0, 1.0], [2.0, 2.0]]
    assert clipped == 0


@pytest.mark.parametrize(
    ("values", "step", "message"),
    [
        ([1.0, np.nan], 0.1, "cannot quantise non-finite values (1 of 2)"),
        ([1.0], 0.0, "quantisation steps must be finite and > 0, got 0.0"),
        ([1.0, 2.0, 3.0], [0.1, 0.2], "step of shape (2,) does not broadcast to values of shape"),
    ],
)
def test_quantise_rejects(values: list[float], step: object, message: str) -> None:
    with pytest.raises(ValueError) as info:
        quantise(values, step)  # type: ignore[arg-type]
    assert str(info.value).startswith(message)


def test_dequantise_needs_integers() -> None:
    with pytest.raises(ValueError, match="expected an integer array, got dtype float64"):
        dequantise(np.array([1.0]), 0.1)


unit_quaternions = hnp.arrays(np.float64, 4, elements=st.floats(-1, 1)).filter(
    lambda q: np.linalg.norm(q) > 0.1
)


@given(unit_quaternions)
def test_quaternion_round_trip_canonical_sign(q: np.ndarray) -> None:
    q = q / np.linalg.norm(q)
    q16 = quaternion_to_int16(q)
    assert q16.dtype == np.int16
    assert q16[3] >= 0
    back = quaternion_from_int16(q16)
    assert np.isclose(np.linalg.norm(back), 1.0)
    # q and -q are the same rotation: compare up to sign.
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-4
    assert quaternion_to_int16(-q).tolist() == q16.tolist()


def test_quaternion_sign_when_w_is_zero() -> None:
    assert quaternion_to_int16([-1.0, 0.0, 0.0, 0.0]).tolist() == [32767, 0, 0, 0]
    assert quaternion_to_int16([0.0, 0.0, 0.0, -2.0]).tolist() == [0, 0, 0, 32767]


def test_quaternion_errors() -> None:
    with pytest.raises(ValueError, match="zero or non-finite norm"):
        quaternion_to_int16([0.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match=r"expected a \(4,\) quaternion"):
        quaternion_to_int16([1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="cannot decode the all-zero quaternion"):
        quaternion_from_int16(np.zeros(4, np.int16))


@given(
    unit_quaternions,
    st.floats(0.2, 5.0),
    hnp.arrays(np.float64, 3, elements=st.floats(-300, 300)),
)
def test_pose_round_trip(q: np.ndarray, scale: float, t: np.ndarray) -> None:
    q = q / np.linalg.norm(q)
    encoded, clipped = encode_pose(Pose(q, scale, t), scale_step=1e-4, translation_step=0.01)
    assert encoded.shape == (8,) and encoded.dtype == np.int16 and clipped == 0
    pose = decode_pose(encoded, scale_step=1e-4, translation_step=0.01)
    assert abs(pose.scale / scale - 1) < 1e-4
    assert np.all(np.abs(pose.translation - t) <= 0.005 + 1e-9)
    assert min(np.abs(pose.quaternion - q).max(), np.abs(pose.quaternion + q).max()) < 1e-4


def test_identity_pose_is_zero_except_w() -> None:
    encoded, _ = encode_pose(Pose(np.array([0.0, 0, 0, 1]), 1.0, np.zeros(3)))
    assert encoded.tolist() == [0, 0, 0, 32767, 0, 0, 0, 0]


def test_pose_translation_clipping_counted() -> None:
    _, clipped = encode_pose(Pose(np.array([0.0, 0, 0, 1]), 1.0, np.array([0, 0, 1e4])))
    assert clipped == 1


def test_pose_rejects_bad_scale() -> None:
    with pytest.raises(ValueError, match="pose scale must be finite and > 0, got 0.0"):
        encode_pose(Pose(np.array([0.0, 0, 0, 1]), 0.0, np.zeros(3)))
