"""Learn the rig's wire basis (models/data/wire_basis.npz) from face videos.

Each clip is tracked frame by frame; its wire parameters, relative to the person's mesh at the
first tracked frame, become vertex displacements of the canonical mesh. The basis is the first
K principal directions of those displacements (uncentred: zero is the face at rest), every clip
weighted equally, mapped back to wire parameters and scaled so that a unit coefficient moves no
vertex more than 1 cm.

    python tools/make_wire_basis.py --k 16 CLIP.mp4 [CLIP ...]

The bundled clip is always included. Clips named here are recorded in the file's ``sources``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from facewire.models.face_channels import WireBasis
from facewire.models.mesh import data_path, load_canonical
from facewire.models.pose import estimate_pose
from facewire.models.rig import load_rig
from facewire.models.wires import WireDeformer
from facewire.sender.capture import VideoSource, demo_clip_path
from facewire.sender.landmarks import LandmarkTracker


def clip_params(path: Path, limit: int | None) -> np.ndarray:
    """(frames, P) wire parameter offsets from rest of every tracked frame of ``path``."""
    rig, canonical, tracker = load_rig(), load_canonical(), LandmarkTracker()
    pose_vertices = np.array(sorted({m.vertex for m in rig.markers_with_role("pose")}))
    wires = None
    rows = []
    with VideoSource(path) as video:
        for frame in video.frames(limit=limit):
            found = tracker.track(frame.image)
            if found is None:
                continue
            points = found.points
            if wires is None:  # the person's mesh at the first tracked frame
                pose = estimate_pose(canonical.vertices[pose_vertices], points[pose_vertices])
                base = pose.inverse(points)
                wires = WireDeformer.from_rig(base, rig)
                continue
            pose = estimate_pose(base[pose_vertices], points[pose_vertices])
            rows.append(wires.fit(pose.inverse(points)) - wires.rest_params())
    if not rows:
        raise ValueError(f"{path}: no tracked face")
    return np.array(rows)


def learn_basis(clips: list[np.ndarray], k: int) -> np.ndarray:
    """(k, P) basis vectors from per-clip parameter offsets (see the module doc)."""
    canonical = load_canonical()
    wires = WireDeformer.from_rig(canonical.vertices, load_rig())
    m = wires.matrix.toarray()  # (3n, P): vertex displacement per parameter
    rows = [(m @ p.T).T / np.sqrt(len(p)) for p in clips]  # each clip weighs the same
    _, _, vt = np.linalg.svd(np.vstack(rows), full_matrices=False)
    directions = vt[:k]  # (k, 3n) vertex-space principal directions
    params = np.linalg.lstsq(m, directions.T, rcond=None)[0].T  # (k, P)
    peak = np.abs(m @ params.T).reshape(-1, 3, k)
    peak = np.linalg.norm(peak, axis=1).max(axis=0)
    return np.asarray(params / peak[:, None])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("clips", nargs="*", type=Path)
    parser.add_argument("--k", type=int, default=16, help="basis size")
    parser.add_argument("--frames", type=int, help="use at most N frames of each clip")
    parser.add_argument("--output", type=Path, default=data_path("wire_basis.npz"))
    args = parser.parse_args(argv)
    paths = [demo_clip_path(), *args.clips]
    clips = []
    for p in paths:
        params = clip_params(p, args.frames)
        print(f"{p.name}: {len(params)} frames", file=sys.stderr)
        clips.append(params)
    vectors = learn_basis(clips, args.k)
    WireBasis(vectors)  # validates the shape
    np.savez_compressed(
        args.output, vectors=vectors, sources=np.array([p.name for p in paths], dtype=str)
    )
    print(f"wrote {args.output}: {vectors.shape[0]} vectors of {vectors.shape[1]} parameters")
    return 0


if __name__ == "__main__":
    sys.exit(main())
