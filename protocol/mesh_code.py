"""The snapshot's mesh, coded small: how far each vertex lies from the canonical mesh's.

A person's face mesh differs from MediaPipe's canonical one (models/data, which both ends
hold; the rig hash covers it) by a few millimetres, and neighbouring vertices differ alike.
So each coordinate is sent as an integer number of ``step`` cm from the canonical vertex
(:func:`quantise`), predicted from the vertex's neighbours already sent, and the prediction's
error is range-coded (protocol/rangecoder.py). At 0.05 mm a 468-vertex face takes about
1.2 KB instead of 2.8 KB as float16: on a 24 kbit/s link the first picture comes 0.5 s sooner.

The order and the prediction (docs/protocol.md, section 2, "Coded vertices"): vertices are
visited breadth first over the triangles' edges, from the lowest-numbered vertex not visited
yet, each vertex's neighbours in ascending order. A vertex's prediction is, per axis, the
mean of its visited neighbours' integers rounded half up (``(sum + count // 2) // count``,
floor division), or 0 when none is visited. Each axis codes its errors with its own
:class:`IntContexts` (``encode_sint``), axis by axis within a vertex.
"""

from __future__ import annotations

from collections import deque
from functools import cache

import numpy as np

from facewire.models.mesh import load_canonical
from facewire.protocol.rangecoder import Decoder, Encoder, IntContexts, decode_sint, encode_sint

#: The snapshot's meta key that says its vertices are coded this way, and their step in cm.
VERTEX_STEP = "vertex_step"
#: The step the sender uses: 0.05 mm (at 0.1 mm the bundled clip's widest jaw came out 10%
#: short: the mouth's fit turns on less than that; tests/test_mouth_opening.py).
STEP_CM = 0.005
#: Coded integers stay within this (a vertex 3 m from the canonical one is not a face).
MAX_STEPS = 1 << 20


class MeshCodeError(ValueError):
    """Coded vertices that do not decode to the canonical mesh's."""


@cache
def _canonical() -> tuple[np.ndarray, tuple[tuple[int, ...], ...], tuple[int, ...]]:
    """The canonical vertices, each vertex's neighbours (ascending) and the visiting order."""
    mesh = load_canonical()
    n = len(mesh.vertices)
    adjacent = tuple(tuple(sorted(mesh.neighbours(v).tolist())) for v in range(n))
    order: list[int] = []
    seen = [False] * n
    for root in range(n):
        if seen[root]:
            continue
        seen[root] = True
        queue = deque([root])
        while queue:
            vertex = queue.popleft()
            order.append(vertex)
            for other in adjacent[vertex]:
                if not seen[other]:
                    seen[other] = True
                    queue.append(other)
    return mesh.vertices.copy(), adjacent, tuple(order)


def vertex_count() -> int:
    return len(_canonical()[0])


def quantise(vertices: np.ndarray, step: float = STEP_CM) -> np.ndarray:
    """``vertices`` as the receiver will decode them (float32, on the step's grid)."""
    canonical = _canonical()[0]
    steps = np.round((np.asarray(vertices, np.float64) - canonical) / step)
    return (canonical + steps * step).astype(np.float32)


def _steps(vertices: np.ndarray, step: float) -> np.ndarray:
    canonical = _canonical()[0]
    if vertices.shape != canonical.shape:
        raise MeshCodeError(f"{vertices.shape} vertices, the canonical mesh has {canonical.shape}")
    steps = np.round((np.asarray(vertices, np.float64) - canonical) / step)
    if not np.all(np.abs(steps) < MAX_STEPS):
        raise MeshCodeError(f"a vertex more than {MAX_STEPS} steps from the canonical mesh")
    return steps.astype(np.int64)


def _prediction(known: dict[int, list[int]], neighbours: tuple[int, ...]) -> list[int]:
    near = [known[v] for v in neighbours if v in known]
    if not near:
        return [0, 0, 0]
    count = len(near)
    return [(sum(p[axis] for p in near) + count // 2) // count for axis in range(3)]


def encode(vertices: np.ndarray, step: float = STEP_CM) -> bytes:
    """The coded form of ``vertices`` ((n, 3) cm, n the canonical mesh's vertex count)."""
    steps = _steps(vertices, step).tolist()
    _, adjacent, order = _canonical()
    encoder = Encoder()
    contexts = [IntContexts() for _ in range(3)]
    known: dict[int, list[int]] = {}
    for vertex in order:
        predicted = _prediction(known, adjacent[vertex])
        for axis in range(3):
            encode_sint(encoder, steps[vertex][axis] - predicted[axis], contexts[axis])
        known[vertex] = steps[vertex]
    return encoder.finish()


def decode(data: bytes, step: float) -> np.ndarray:
    """The vertices ``data`` codes (float32 cm); MeshCodeError where a value is out of range.

    Any bytes decode to some mesh (the code has no redundancy, as float coordinates have
    none): the receiver's own checks of the mesh apply to it as to any other."""
    canonical, adjacent, order = _canonical()
    if not (np.isfinite(step) and step > 0):
        raise MeshCodeError(f"vertex step {step} is not a positive number")
    decoder = Decoder(data)
    contexts = [IntContexts() for _ in range(3)]
    known: dict[int, list[int]] = {}
    for vertex in order:
        predicted = _prediction(known, adjacent[vertex])
        value = [predicted[axis] + decode_sint(decoder, contexts[axis]) for axis in range(3)]
        if any(abs(v) >= MAX_STEPS for v in value):
            raise MeshCodeError(f"vertex {vertex} more than {MAX_STEPS} steps from the canonical")
        known[vertex] = value
    steps = np.array([known[v] for v in range(len(canonical))], np.float64)
    return (canonical + steps * step).astype(np.float32)
