"""Per-frame cost of the wire deformer and blending at 468 and ~7,257 vertices.

    .venv/bin/python benchmarks/bench_deformers.py [--repeats N]

Prints construction time, deform and fit milliseconds per frame (median over N frames
with fresh random parameters), on the canonical mesh and on its 2-level Loop subdivision,
driven by the bundled rig.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from facewire.models.blending import blend
from facewire.models.mesh import FaceMesh, load_canonical
from facewire.models.rig import load_rig
from facewire.models.subdivision import loop_subdivide
from facewire.models.wires import WireDeformer


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def bench_wires(mesh: FaceMesh, repeats: int) -> None:
    rig = load_rig()
    t0 = time.perf_counter()
    w = WireDeformer.from_rig(mesh.vertices, rig)
    build = time.perf_counter() - t0
    t0 = time.perf_counter()
    w.prepare_fit()
    pinv = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    params = [w.rest_params() + 0.1 * rng.normal(size=w.n_params) for _ in range(16)]
    targets = [w.deform(p) for p in params]
    i = iter(range(10**9))
    deform_ms = _median_ms(lambda: w.deform(params[next(i) % 16]), repeats)
    fit_ms = _median_ms(lambda: w.fit(targets[next(i) % 16]), repeats)
    err = max(float(np.abs(w.fit(t) - p).max()) for t, p in zip(targets, params, strict=True))
    print(
        f"wires  n={mesh.n_vertices:5d}  curves={w.n_curves}  params={w.n_params}  "
        f"nnz(A)={w.matrix.nnz}  build {1e3 * build:7.1f} ms  pinv {1e3 * pinv:7.1f} ms  "
        f"deform {deform_ms:.3f} ms/frame  fit {fit_ms:.3f} ms/frame  "
        f"round-trip max|dp| {err:.1e}  cond(A) {w.condition:.1f}"
    )


def bench_blending(mesh: FaceMesh, repeats: int) -> None:
    w = WireDeformer.from_rig(mesh.vertices, load_rig())
    groups = w.feature_groups()
    rng = np.random.default_rng(1)
    p0, p1 = (w.rest_params() + 0.1 * rng.normal(size=w.n_params) for _ in range(2))
    ms = _median_ms(lambda: w.deform(blend(p0, p1, 0.3, groups)), repeats)
    print(f"blend+deform  n={mesh.n_vertices:5d}  {ms:.3f} ms/frame")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=500)
    args = parser.parse_args()
    coarse = load_canonical()
    fine, _ = loop_subdivide(coarse, 2)
    for mesh in (coarse, fine):
        bench_wires(mesh, args.repeats)
        bench_blending(mesh, args.repeats)


if __name__ == "__main__":
    main()
