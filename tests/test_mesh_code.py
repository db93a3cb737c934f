"""The snapshot's mesh coded against the canonical one (protocol/mesh_code.py)."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

from facewire.models.mesh import load_canonical
from facewire.protocol import mesh_code
from facewire.protocol.packets import PacketError, Snapshot, decode
from facewire.protocol.rangecoder import Decoder, IntContexts, decode_sint

CANONICAL = load_canonical()


def a_face(seed: int = 1) -> np.ndarray:
    """The canonical mesh bent smoothly, as a person's face differs from it (a few mm)."""
    rng = np.random.default_rng(seed)
    v = CANONICAL.vertices
    bend = rng.normal(0, 0.05, (3, 3))
    return v + np.tanh(v / 8.0) @ bend + rng.normal(0, 0.02, v.shape)


def decode_as_documented(data: bytes, step: float) -> np.ndarray:
    """docs/protocol.md section 2, "Coded vertices", read on its own (only the range coder,
    section 5, is taken from the package)."""
    n = len(CANONICAL.vertices)
    neighbours: list[set[int]] = [set() for _ in range(n)]
    for tri in CANONICAL.triangles.tolist():
        for a in tri:
            neighbours[a] |= set(tri) - {a}
    order, visited = [], [False] * n
    for root in range(n):
        if visited[root]:
            continue
        visited[root], todo = True, deque([root])
        while todo:
            vertex = todo.popleft()
            order.append(vertex)
            for other in sorted(neighbours[vertex]):
                if not visited[other]:
                    visited[other] = True
                    todo.append(other)
    dec = Decoder(data)
    contexts = [IntContexts(), IntContexts(), IntContexts()]
    q: dict[int, list[int]] = {}
    for vertex in order:
        coded = [q[o] for o in neighbours[vertex] if o in q]
        values = []
        for axis in range(3):
            total = sum(c[axis] for c in coded)
            p = (total + len(coded) // 2) // len(coded) if coded else 0
            values.append(p + decode_sint(dec, contexts[axis]))
        q[vertex] = values
    steps = np.array([q[i] for i in range(n)], np.float64)
    return (CANONICAL.vertices + steps * step).astype(np.float32)


@pytest.mark.parametrize("step", [0.01, 0.025, 0.1])
def test_round_trip_is_exact_on_the_grid(step: float) -> None:
    face = mesh_code.quantise(a_face(), step)
    assert np.abs(face - a_face()).max() <= step / 2 + 1e-5
    data = mesh_code.encode(face, step)
    assert np.array_equal(mesh_code.decode(data, step), face)
    assert np.array_equal(decode_as_documented(data, step), face)


def test_a_face_takes_a_third_of_float16() -> None:
    data = mesh_code.encode(mesh_code.quantise(a_face()), mesh_code.STEP_CM)
    assert len(data) < 0.5 * 6 * len(CANONICAL.vertices)


def test_the_snapshot_carries_the_coded_mesh() -> None:
    face = mesh_code.quantise(a_face())
    snapshot = Snapshot(
        1,
        0,
        64,
        48,
        30.0,
        face,
        b"",
        b"",
        [("wire", 4, 0.1)],
        "0" * 64,
        30,
        [(0, 0, 0, 0)],
        {mesh_code.VERTEX_STEP: mesh_code.STEP_CM},
    )
    wire = bytes(snapshot)
    assert len(wire) < 6 * len(face)  # float16 alone would take more than the whole packet
    got = decode(wire)
    assert isinstance(got, Snapshot) and np.array_equal(got.vertices, face)


def test_a_mesh_that_is_not_the_canonicals_shape_is_refused() -> None:
    with pytest.raises(PacketError, match="coded against the canonical mesh's 468"):
        Snapshot(
            1, 0, 64, 48, 30.0, np.zeros((10, 3)), b"", b"", [("wire", 4, 0.1)], "0" * 64, 30,
            [(0, 0, 0, 0)], {mesh_code.VERTEX_STEP: mesh_code.STEP_CM},
        )  # fmt: skip
    with pytest.raises(mesh_code.MeshCodeError, match="more than"):
        mesh_code.encode(CANONICAL.vertices + 1e5, mesh_code.STEP_CM)


def test_any_bytes_decode_to_a_mesh_or_a_clear_error() -> None:
    rng = np.random.default_rng(7)
    for size in [0, 1, 5, 100, 1000, 3000]:
        for _ in range(5):
            try:
                mesh = mesh_code.decode(rng.bytes(size), mesh_code.STEP_CM)
            except mesh_code.MeshCodeError as exc:
                assert "steps from the canonical" in str(exc)
            else:
                assert mesh.shape == CANONICAL.vertices.shape and np.isfinite(mesh).all()
