"""Feature-wise non-uniform blending of wire parameters (seed 000, section 5, Fig. 4-6).

Between two parameter vectors p0 and p1 (e.g. two extracted expression templates, or two
received keyframes), each facial feature follows its own blending function g: [0, 1] ->
[0, 1] with g(0) = 0 and g(1) = 1, so that p = p0 + g_feature(t) (p1 - p0). The seed's
example: g(t) = sqrt(t) for the eyes (fast at first) and g(t) = t^3 for the mouth (slow at
first); every other feature blends linearly.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping

import numpy as np

logger = logging.getLogger(__name__)

BlendFunction = Callable[[float], float]


def linear(t: float) -> float:
    return t


def sqrt(t: float) -> float:
    return float(np.sqrt(t))


def cube(t: float) -> float:
    return t**3


def smoothstep(t: float) -> float:
    return t * t * (3.0 - 2.0 * t)


BLEND_FUNCTIONS: dict[str, BlendFunction] = {
    "linear": linear,
    "sqrt": sqrt,
    "cube": cube,
    "smoothstep": smoothstep,
}

# Fig. 6 of seed 000; features not named here blend linearly.
DEFAULT_FEATURE_FUNCTIONS: dict[str, str] = {"eyes": "sqrt", "mouth": "cube"}


def resolve(function: str | BlendFunction) -> BlendFunction:
    """A blending function from its registry name or the callable itself."""
    if callable(function):
        return function
    try:
        return BLEND_FUNCTIONS[function]
    except KeyError:
        raise ValueError(
            f"unknown blending function {function!r}; known: {', '.join(BLEND_FUNCTIONS)}"
        ) from None


def blend(
    p0: np.ndarray,
    p1: np.ndarray,
    t: float,
    groups: Mapping[str, np.ndarray],
    functions: Mapping[str, str | BlendFunction] | None = None,
    default: str | BlendFunction = "linear",
) -> np.ndarray:
    """Blend parameter vectors p0, p1 (P,) at time t in [0, 1], feature by feature.

    groups : feature name -> indices into the parameter vector (e.g.
        WireDeformer.feature_groups()); indices in no group use ``default``.
    functions : feature name -> blending function (registry name or callable), on top of
        DEFAULT_FEATURE_FUNCTIONS (eyes sqrt, mouth cube); other features use ``default``.
    Returns (P,) float64; t = 0 gives p0 and t = 1 gives p1 exactly.
    """
    a = np.asarray(p0, dtype=np.float64)
    b = np.asarray(p1, dtype=np.float64)
    if a.ndim != 1 or a.shape != b.shape:
        raise ValueError(f"expected two (P,) parameter vectors, got {a.shape} and {b.shape}")
    t = float(t)
    if not 0.0 <= t <= 1.0:
        raise ValueError(f"blend time must lie in [0, 1], got {t}")
    chosen: dict[str, str | BlendFunction] = dict(DEFAULT_FEATURE_FUNCTIONS)
    if functions is not None:
        chosen.update(functions)
    g = np.full(a.shape, resolve(default)(t), dtype=np.float64)
    for feature, idx in groups.items():
        idx = np.asarray(idx, dtype=np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= a.size):
            raise ValueError(
                f"group {feature!r}: index {int(idx.max())} out of range 0..{a.size - 1}"
            )
        g[idx] = resolve(chosen.get(feature, default))(t)
    # Exact endpoints whatever the functions' rounding.
    if t == 0.0:
        return a.copy()
    if t == 1.0:
        return b.copy()
    return a + g * (b - a)
