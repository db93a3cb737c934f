"""How well `facewire wires extract|apply` rebuilds an expression not made with wires.

Usage: python benchmarks/bench_wirestool.py

The template is the canonical mesh deformed by the rig's GDEs (seed 002): brows up 0.5 cm and
the mouth corners up and out, so the wire fit (seed 000) has to approximate, not invert.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from facewire.models.gde import GdeSet
from facewire.models.mesh import load_canonical, load_obj, save_obj
from facewire.models.rig import load_rig
from facewire.wirestool import apply, extract


def main() -> None:
    base = load_canonical()
    gdes = GdeSet.from_rig(base, load_rig())
    d = np.zeros((len(gdes.names), 3))
    for name in gdes.names:
        if "brow" in name:
            d[gdes.index(name)] = [0.0, 0.5, 0.0]
    d[gdes.index("mouth_left")] = [0.3, 0.5, 0.0]
    d[gdes.index("mouth_right")] = [-0.3, 0.5, 0.0]
    template = base.with_vertices(gdes.deform(base.vertices, d))
    with tempfile.TemporaryDirectory() as tmp:
        paths = {k: Path(tmp) / f"{k}.obj" for k in ("base", "template", "out")}
        save_obj(base, paths["base"])
        save_obj(template, paths["template"])
        extract(paths["base"], paths["template"], Path(tmp) / "params.json")
        apply(paths["base"], Path(tmp) / "params.json", paths["out"])
        rebuilt = load_obj(paths["out"])
    motion = np.linalg.norm(template.vertices - base.vertices, axis=1)
    error = np.linalg.norm(rebuilt.vertices - template.vertices, axis=1)
    print(f"template motion: RMS {np.sqrt(np.mean(motion**2)):.3f} cm, max {motion.max():.3f} cm")
    print(f"rebuild error:   RMS {np.sqrt(np.mean(error**2)):.3f} cm, max {error.max():.3f} cm")


if __name__ == "__main__":
    main()
