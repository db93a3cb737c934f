"""Quantisation of parameters and pose to int16 (pure numpy).

A value ``x`` with step ``d`` travels as ``q = clip(rint(x / d), -32767, 32767)`` and comes back
as ``q * d``; the error is at most ``d / 2`` for values inside ``+-32767 d``. Values outside are
clipped and counted, so a sender can log or widen its steps.

The pose travels as eight int16, ``[qx, qy, qz, qw, s, tx, ty, tz]``:

- a unit quaternion in scalar-last order (as :class:`scipy.spatial.transform.Rotation`),
  sign-canonicalised so that ``qw >= 0``, each component times 32767;
- ``s = rint(ln(scale) / scale_step)``, a log scale so that zooming in and out are symmetric;
- ``t = rint(translation / translation_step)``, translation in the pose's target units
  (facewire's poses map the model into image pixels).
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from protocol.constants import (
    DEFAULT_SCALE_STEP,
    DEFAULT_TRANSLATION_STEP_CM,
    INT16_LIMIT,
)

logger = logging.getLogger(__name__)


def _steps(step: float | ArrayLike, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """Validate a scalar or per-element step and broadcast it to ``shape``."""
    steps = np.asarray(step, dtype=np.float64)
    if not np.all(np.isfinite(steps)) or not np.all(steps > 0):
        raise ValueError(f"quantisation steps must be finite and > 0, got {step!r}")
    try:
        return np.broadcast_to(steps, shape)
    except ValueError:
        raise ValueError(
            f"step of shape {steps.shape} does not broadcast to values of shape {shape}"
        ) from None


def quantise(values: ArrayLike, step: float | ArrayLike) -> tuple[NDArray[np.int16], int]:
    """Quantise floats to int16 with rounding to nearest and clipping.

    Parameters
    ----------
    values : (...) float array, any units
    step : float or array broadcastable to ``values``, same units as ``values``, > 0

    Returns
    -------
    q : int16 array, same shape as ``values``, in [-32767, 32767]
    clipped : how many values were outside the representable range and were clipped
    """
    x = np.asarray(values, dtype=np.float64)
    if not np.all(np.isfinite(x)):
        bad = int(np.count_nonzero(~np.isfinite(x)))
        raise ValueError(f"cannot quantise non-finite values ({bad} of {x.size})")
    scaled = np.rint(x / _steps(step, x.shape))
    out_of_range = np.abs(scaled) > INT16_LIMIT
    clipped = int(np.count_nonzero(out_of_range))
    if clipped:
        logger.debug("quantise: %d of %d values clipped", clipped, x.size)
    q = np.clip(scaled, -INT16_LIMIT, INT16_LIMIT).astype(np.int16)
    return q, clipped


def dequantise(q: ArrayLike, step: float | ArrayLike) -> NDArray[np.float64]:
    """Inverse of :func:`quantise`: ``q * step`` as float64 with the shape of ``q``."""
    qa = np.asarray(q)
    if not np.issubdtype(qa.dtype, np.integer):
        raise ValueError(f"expected an integer array, got dtype {qa.dtype}")
    return qa.astype(np.float64) * _steps(step, qa.shape)


def quaternion_to_int16(quaternion: ArrayLike) -> NDArray[np.int16]:
    """Unit quaternion (x, y, z, w) -> (4,) int16.

    The quaternion is normalised first, then its sign is chosen so that ``w >= 0`` (``q`` and
    ``-q`` are the same rotation); when ``w == 0`` the first non-zero component is made positive.
    """
    q = np.asarray(quaternion, dtype=np.float64)
    if q.shape != (4,):
        raise ValueError(f"expected a (4,) quaternion (x, y, z, w), got shape {q.shape}")
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm == 0.0:
        raise ValueError(f"cannot encode quaternion {q.tolist()}: zero or non-finite norm")
    q = q / norm
    order = (3, 0, 1, 2)
    lead = next(float(q[i]) for i in order if q[i] != 0.0)
    if lead < 0:
        q = -q
    return np.rint(q * INT16_LIMIT).astype(np.int16)


def quaternion_from_int16(q16: ArrayLike) -> NDArray[np.float64]:
    """(4,) int16 -> unit quaternion (x, y, z, w), float64, renormalised."""
    q = np.asarray(q16)
    if q.shape != (4,) or not np.issubdtype(q.dtype, np.integer):
        raise ValueError(f"expected (4,) integer quaternion, got {q.dtype} array of {q.shape}")
    qf = q.astype(np.float64)
    norm = float(np.linalg.norm(qf))
    if norm == 0.0:
        raise ValueError("cannot decode the all-zero quaternion")
    return qf / norm


class Pose(NamedTuple):
    """Rigid head pose with uniform scale, in model space.

    quaternion : (4,) float64, unit, scalar-last (x, y, z, w)
    scale : float, > 0, uniform scale of the model
    translation : (3,) float64, cm
    """

    quaternion: NDArray[np.float64]
    scale: float
    translation: NDArray[np.float64]


def encode_pose(
    pose: Pose,
    scale_step: float = DEFAULT_SCALE_STEP,
    translation_step: float = DEFAULT_TRANSLATION_STEP_CM,
) -> tuple[NDArray[np.int16], int]:
    """Pose -> ((8,) int16 ``[qx, qy, qz, qw, s, tx, ty, tz]``, number of clipped values).

    ``scale_step`` is in natural-log units, ``translation_step`` in cm.
    """
    if not (np.isfinite(pose.scale) and pose.scale > 0):
        raise ValueError(f"pose scale must be finite and > 0, got {pose.scale!r}")
    t = np.asarray(pose.translation, dtype=np.float64)
    if t.shape != (3,):
        raise ValueError(f"expected (3,) translation in cm, got shape {t.shape}")
    s_q, s_clipped = quantise(np.array([np.log(pose.scale)]), scale_step)
    t_q, t_clipped = quantise(t, translation_step)
    out = np.concatenate([quaternion_to_int16(pose.quaternion), s_q, t_q]).astype(np.int16)
    return out, s_clipped + t_clipped


def decode_pose(
    q8: ArrayLike,
    scale_step: float = DEFAULT_SCALE_STEP,
    translation_step: float = DEFAULT_TRANSLATION_STEP_CM,
) -> Pose:
    """(8,) int16 ``[qx, qy, qz, qw, s, tx, ty, tz]`` -> :class:`Pose`."""
    q = np.asarray(q8)
    if q.shape != (8,) or not np.issubdtype(q.dtype, np.integer):
        raise ValueError(f"expected (8,) integer pose, got {q.dtype} array of shape {q.shape}")
    scale = float(np.exp(dequantise(q[4:5], scale_step)[0]))
    return Pose(quaternion_from_int16(q[:4]), scale, dequantise(q[5:8], translation_step))


def wire_steps(
    s_step: float, q_step: float, wire_layout: list[tuple[str, int]] | tuple[tuple[str, int], ...]
) -> NDArray[np.float64]:
    """Per-element steps of a wire parameter vector laid out as in ``Frame.params``.

    The vector is ``s_j - 1`` for every curve j (``s_step``), then each curve's control
    point displacements ``(n_ctrl_j, 3)`` flattened (``q_step``, cm).
    """
    n_q = 3 * sum(int(n) for _, n in wire_layout)
    return np.concatenate([np.full(len(wire_layout), float(s_step)), np.full(n_q, float(q_step))])
