"""Per-frame cost of the GDE set and the lip homotopy sweep at two mesh sizes.

    .venv/bin/python benchmarks/bench_gde_homotopy.py [--frames 2000]

Uses the bundled rig (all its GDEs, its lip rings) on the canonical mesh and on its
2-level Loop subdivision (edge-depth sizes scaled by 4 there, since every level halves
the edges). Prints build time and milliseconds per frame (median over frames).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from facewire.models.gde import GdeDef, GdeSet, rig_mouth_seam
from facewire.models.homotopy import MouthRig
from facewire.models.mesh import FaceMesh, load_canonical
from facewire.models.rig import load_rig
from facewire.models.subdivision import loop_subdivide


def per_frame_ms(fn, frames: int) -> float:
    samples = np.empty(frames)
    for i in range(frames):
        t0 = time.perf_counter()
        fn(i)
        samples[i] = time.perf_counter() - t0
    return float(np.median(samples) * 1e3)


def run(mesh: FaceMesh, depth_scale: int, frames: int) -> None:
    rig = load_rig()
    specs = [
        GdeDef(
            s.name, s.control_vertex, s.size * (depth_scale if s.metric == "edges" else 1), s.metric
        )
        for s in rig.gdes
    ]
    t0 = time.perf_counter()
    gdes = GdeSet(mesh, specs, cut_edges=rig_mouth_seam(mesh, rig.lips))
    t1 = time.perf_counter()
    mouth = MouthRig.from_rig(mesh, rig)
    t2 = time.perf_counter()
    rng = np.random.default_rng(0)
    disp = rng.normal(scale=0.2, size=(64, len(gdes), 3))
    lips = rng.normal(scale=0.2, size=(64, 4, 3))
    base = mesh.vertices

    gde_ms = per_frame_ms(lambda i: gdes.deform(base, disp[i % 64]), frames)
    sweep_ms = per_frame_ms(lambda i: mouth.deform(base, lips[i % 64], 0.5), frames)
    both_ms = per_frame_ms(
        lambda i: mouth.deform(gdes.deform(base, disp[i % 64]), lips[i % 64], 0.5), frames
    )
    print(
        f"{mesh.n_vertices:6d} vertices: {len(gdes)} GDEs, {gdes.matrix.nnz} weights "
        f"(build {1e3 * (t1 - t0):.1f} ms); mouth {len(mouth.ring_vertices)} ring + "
        f"{len(mouth.follow_vertices)} follow vertices (build {1e3 * (t2 - t1):.1f} ms)"
    )
    print(
        f"        per frame: GDE deform {gde_ms:.3f} ms, homotopy sweep {sweep_ms:.3f} ms, "
        f"both {both_ms:.3f} ms"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000)
    args = parser.parse_args()
    coarse = load_canonical()
    fine, _ = loop_subdivide(coarse, 2)
    run(coarse, 1, args.frames)
    run(fine, 4, args.frames)


if __name__ == "__main__":
    main()
