"""Receiver render speed and sender unwrap speed at 640x480 (EGL, Mesa llvmpipe on CPU).

    PYOPENGL_PLATFORM=egl .venv/bin/python benchmarks/bench_render.py [--frames 200]

Prints, for the canonical mesh (468 vertices) and its Loop subdivision (2 levels, 7,257
vertices): frames per second of FaceRenderer.render with the vertex buffer updated in place
(the shipped path) against rebuilding the pyrender mesh every frame, with and without
compositing over a background; and the time of UvRasteriser construction, unwrap and
make_background.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pyrender

from facewire.models.mesh import FaceMesh, load_canonical
from facewire.receiver.render import FaceRenderer
from facewire.sender.texture import UvRasteriser, make_background

W, H = 640, 480


def subdivided(mesh: FaceMesh) -> FaceMesh:
    from facewire.models.subdivision import loop_subdivide

    return loop_subdivide(mesh, 2)[0]


def texture(size: int = 512) -> np.ndarray:
    rng = np.random.default_rng(0)
    return rng.integers(0, 256, (size, size, 3), dtype=np.uint8)


def poses(mesh: FaceMesh, n: int) -> list[np.ndarray]:
    """n image-space vertex sets: a face nodding and turning, about 240 px wide."""
    out = []
    for i in range(n):
        a, b = 0.4 * np.sin(i / 15.0), 0.2 * np.sin(i / 23.0)
        ry = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
        rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
        r = np.diag([1.0, -1.0, -1.0]) @ ry @ rx
        out.append(14.0 * mesh.vertices @ r.T + [320 + 20 * np.sin(i / 9.0), 250, 500])
    return out


def rebuild_every_frame(renderer: FaceRenderer) -> None:
    """Swap the in-place upload for the alternative: a new pyrender Mesh every frame."""

    def set_positions(gl_positions: np.ndarray) -> None:
        scene = renderer._scene
        scene.remove_node(renderer._mesh_node)
        renderer._primitive = renderer._make_primitive(gl_positions)
        renderer._mesh_node = scene.add(pyrender.Mesh([renderer._primitive]))

    renderer._set_positions = set_positions  # type: ignore[method-assign]


def fps(fn, frames: list[np.ndarray]) -> float:
    fn(frames[0])  # first frame uploads buffers and compiles shaders
    t = time.perf_counter()
    for v in frames:
        fn(v)
    return len(frames) / (time.perf_counter() - t)


def report(label: str, value: float, unit: str) -> None:
    print(f"  {label:<48s}: {value:8.2f} {unit}")


def bench_mesh(name: str, mesh: FaceMesh, n_frames: int) -> None:
    frames = poses(mesh, n_frames)
    tex = texture()
    bg = np.full((H, W, 3), 90, np.uint8)
    print(f"{name}: {mesh.n_vertices} vertices, {len(mesh.triangles)} triangles")
    with FaceRenderer(W, H, mesh.triangles, mesh.uvs, tex) as r:
        report("render, in-place vertex upload, no background", fps(r.render, frames), "fps")
        r.set_background(bg)
        report("render, in-place vertex upload, background", fps(r.render, frames), "fps")
        r.set_background(None)
        rebuild_every_frame(r)
        report("render, rebuild pyrender mesh every frame", fps(r.render, frames), "fps")
        t = time.perf_counter()
        for _ in range(20):
            r.set_texture(tex)
        report("set_texture 512x512 (in-place upload)", (time.perf_counter() - t) / 20 * 1e3, "ms")

    t = time.perf_counter()
    ras = UvRasteriser(mesh.triangles, mesh.uvs, 512)
    report("UvRasteriser(512) construction", (time.perf_counter() - t) * 1e3, "ms")
    frame = texture(W)[:H]
    ras.unwrap(frame, frames[0])
    t = time.perf_counter()
    for v in frames[:20]:
        ras.unwrap(frame, v)
    report("unwrap 512x512 from 640x480", (time.perf_counter() - t) / 20 * 1e3, "ms")
    t = time.perf_counter()
    for v in frames[:5]:
        make_background(frame, v, mesh.triangles)
    report("make_background 640x480", (time.perf_counter() - t) / 5 * 1e3, "ms")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=200)
    args = ap.parse_args()
    mesh = load_canonical()
    bench_mesh("canonical", mesh, args.frames)
    bench_mesh("loop x2", subdivided(mesh), args.frames)


if __name__ == "__main__":
    main()
