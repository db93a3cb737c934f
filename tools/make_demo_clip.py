"""Make the bundled demo clip (sender/data/demo_clip.mp4) and its ground truth.

The clip is rendered from the face model itself, so every frame's wire parameters, head
pose and marker positions are known exactly (sender/data/demo_clip_truth.npz):

1. The astronaut photo (skimage.data.astronaut(), public domain, NASA) is scaled and
   cropped to 640x480 with the face ~200 px wide and centred; the landmark tracker finds
   her face (L0), the person mesh is P = estimate_pose(canonical, L0).inverse(L0), the
   texture is unwrapped from the framed photo and the background is the framed photo
   with the face filled in from its surroundings.
2. A scripted 10 s performance (300 frames at 30 fps) is expressed as wire parameters on
   P: neutral, smile, surprise, blinks, talking, neutral, with keyframes interpolated by
   models.blending.blend (feature-wise), plus a smooth head motion.
3. Each frame is rendered with the receiver's FaceRenderer over the background, and the
   rig's markers that face the camera are drawn as small dots coloured by role.

Deterministic; run once and commit the outputs:
    PYOPENGL_PLATFORM=egl .venv/bin/python tools/make_demo_clip.py
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from facewire.models.blending import blend, smoothstep  # noqa: E402
from facewire.models.mesh import FaceMesh, load_canonical  # noqa: E402
from facewire.models.pose import Pose, estimate_pose  # noqa: E402
from facewire.models.rig import Rig, load_rig  # noqa: E402
from facewire.models.wires import WireDeformer  # noqa: E402
from facewire.receiver.render import FaceRenderer  # noqa: E402
from facewire.sender.landmarks import LandmarkTracker  # noqa: E402
from facewire.sender.texture import UvRasteriser, make_background  # noqa: E402

WIDTH, HEIGHT, FPS, N_FRAMES = 640, 480, 30, 300
FACE_WIDTH = 200.0  # px, target width of the face (landmark extent) in the clip
TEXTURE_SIZE = 512
MARKER_RADIUS = 3
ROLE_COLOURS = {"pose": (0, 200, 0), "deform": (230, 80, 0), "mouth": (0, 0, 230)}  # BGR
BACKGROUND_DILATE = 0.025  # make_background's hole growth: small, so little grey halo
MIN_FACING = 0.2  # cosine between a marker's normal and the view direction to draw it

OUT_DIR = ROOT / "sender" / "data"
CLIP = OUT_DIR / "demo_clip.mp4"
TRUTH = OUT_DIR / "demo_clip_truth.npz"

# Timeline (frame numbers at 30 fps). Frames 0..NEUTRAL_END are neutral and still.
NEUTRAL_END = 30
# (frame, expression) keyframes of the base expression track, blended pairwise.
KEYFRAMES: list[tuple[int, str]] = [
    (0, "neutral"),
    (36, "neutral"),
    (54, "smile"),
    (78, "smile"),
    (94, "neutral"),
    (112, "neutral"),
    (126, "surprise"),
    (150, "surprise"),
    (166, "neutral"),
    (262, "neutral"),
    (276, "smile"),
    (288, "neutral"),
    (N_FRAMES - 1, "neutral"),
]
BLINKS = [100, 140, 172, 212, 250]  # frame at which each blink is fully closed
BLINK_HALF = 2  # frames to close (and to open): ~5 frames = 167 ms per blink
TALK = (180, 252)  # frames of talking mouth


@dataclass(frozen=True)
class Scene:
    frame: np.ndarray  # (H, W, 3) framed photo, BGR
    landmarks: np.ndarray  # (468, 3) L0, image px
    pose0: Pose
    person: np.ndarray  # (468, 3) P, cm, model space
    texture: np.ndarray
    background: np.ndarray


def frame_photo(photo_bgr: np.ndarray, tracker: LandmarkTracker) -> np.ndarray:
    """Scale and crop the photo to WIDTHxHEIGHT with the face FACE_WIDTH wide and centred."""
    tracker.reset()
    tracker.track(photo_bgr)
    lm = tracker.track(photo_bgr)
    if lm is None:
        raise RuntimeError("no face found in the source photo")
    pts = lm.points[:, :2]
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    k = FACE_WIDTH / float(hi[0] - lo[0])
    centre = (lo + hi) / 2.0 * k
    # Affine: scale by k, then put the face centre a little above the frame centre.
    target = np.array([WIDTH / 2.0, HEIGHT / 2.0 - 10.0])
    m = np.array([[k, 0.0, target[0] - centre[0]], [0.0, k, target[1] - centre[1]]])
    return cv2.warpAffine(
        photo_bgr, m, (WIDTH, HEIGHT), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )


def build_scene(mesh: FaceMesh, tracker: LandmarkTracker) -> Scene:
    from skimage import data

    photo = cv2.cvtColor(data.astronaut(), cv2.COLOR_RGB2BGR)
    frame = frame_photo(photo, tracker)
    tracker.reset()
    tracker.track(frame)
    lm = tracker.track(frame)  # second pass: the tracker's own crop
    if lm is None:
        raise RuntimeError("no face found in the framed photo")
    l0 = lm.points.astype(np.float64)
    pose0 = estimate_pose(mesh.vertices, l0)
    person = pose0.inverse(l0)
    texture, _ = UvRasteriser(mesh.triangles, mesh.uvs, TEXTURE_SIZE).unwrap(frame, l0)
    background = make_background(frame, l0, mesh.triangles, BACKGROUND_DILATE)
    return Scene(frame, l0, pose0, person, texture, background)


# -- expressions as wire parameters ---------------------------------------------------


class Expressions:
    """Wire parameter vectors for the scripted expressions, on the person mesh."""

    def __init__(self, deformer: WireDeformer) -> None:
        self.d = deformer
        self.index = {n: j for j, n in enumerate(deformer.names)}
        self.rest = deformer.rest_params()
        self.groups = deformer.feature_groups()

    def ref(self, name: str) -> np.ndarray:
        return np.asarray(self.d.reference_control_points[self.index[name]])

    def with_q(self, base: np.ndarray, moves: dict[str, np.ndarray]) -> np.ndarray:
        """base params with the q of the named curves increased by moves (n_ctrl, 3)."""
        s, q = self.d.split_params(base)
        for name, dq in moves.items():
            q[self.index[name]] = q[self.index[name]] + dq
        return self.d.join_params(s, q)

    @staticmethod
    def bump(n: int, ends: float = 0.0) -> np.ndarray:
        """(n,) weights: 1 in the middle of a curve, ``ends`` at its first and last point."""
        x = np.linspace(-1.0, 1.0, n)
        return ends + (1.0 - ends) * (1.0 - x**2)

    def smile(self) -> np.ndarray:
        moves: dict[str, np.ndarray] = {}
        for lip in ("upper_lip", "lower_lip"):
            r = self.ref(lip)
            n = len(r)
            x = np.linspace(-1.0, 1.0, n)
            corner = np.abs(x) ** 2  # corners move most
            side = np.sign(r[:, 0] - r[:, 0].mean())
            dq = np.zeros((n, 3))
            dq[:, 0] = 0.4 * corner * side  # out
            dq[:, 1] = 0.6 * corner  # up
            dq[:, 2] = -0.15 * corner  # back, round the cheek
            if lip == "lower_lip":
                dq[:, 1] += 0.05 * (1.0 - corner)
            moves[lip] = dq
        for cheek in ("cheek_right", "cheek_left"):
            n = len(self.ref(cheek))
            dq = np.zeros((n, 3))
            dq[:, 1] = 0.3
            dq[:, 2] = 0.1
            moves[cheek] = dq
        for nl in ("nasolabial_right", "nasolabial_left"):
            r = self.ref(nl)
            side = np.sign(r[:, 0].mean())
            dq = np.zeros((len(r), 3))
            dq[:, 0] = 0.15 * side
            dq[:, 1] = 0.2
            moves[nl] = dq
        # Eyes narrow a little in a real smile: lower lids up.
        for lid in ("lower_lid_right", "lower_lid_left"):
            n = len(self.ref(lid))
            dq = np.zeros((n, 3))
            dq[:, 1] = 0.06 * self.bump(n)
            moves[lid] = dq
        return self.with_q(self.rest, moves)

    def surprise(self) -> np.ndarray:
        moves: dict[str, np.ndarray] = {}
        for brow in ("brow_right", "brow_left"):
            n = len(self.ref(brow))
            dq = np.zeros((n, 3))
            dq[:, 1] = 0.6
            moves[brow] = dq
        n = len(self.ref("forehead"))
        moves["forehead"] = np.column_stack([np.zeros(n), np.full(n, 0.25), np.zeros(n)])
        for lid in ("upper_lid_right", "upper_lid_left"):
            n = len(self.ref(lid))
            dq = np.zeros((n, 3))
            dq[:, 1] = 0.15 * self.bump(n)
            moves[lid] = dq
        for lid in ("lower_lid_right", "lower_lid_left"):
            n = len(self.ref(lid))
            dq = np.zeros((n, 3))
            dq[:, 1] = -0.05 * self.bump(n)
            moves[lid] = dq
        moves.update(self.jaw(1.0))
        return self.with_q(self.rest, moves)

    def jaw(self, amount: float) -> dict[str, np.ndarray]:
        """Lower lip and chin down (mouth open) by ``amount`` (1 = ~0.7 cm at the lip)."""
        n = len(self.ref("lower_lip"))
        lip = np.zeros((n, 3))
        lip[:, 1] = -0.8 * amount * self.bump(n, ends=0.1)
        lip[:, 2] = -0.1 * amount * self.bump(n)
        n = len(self.ref("chin"))
        chin = np.zeros((n, 3))
        chin[:, 1] = -0.8 * amount * self.bump(n, ends=0.4)
        chin[:, 2] = -0.15 * amount
        n = len(self.ref("upper_lip"))
        upper = np.zeros((n, 3))
        upper[:, 1] = 0.08 * amount * self.bump(n)
        return {"lower_lip": lip, "chin": chin, "upper_lip": upper}

    def closed_eyes(self, params: np.ndarray) -> np.ndarray:
        """params with each upper lid wire moved onto its (current) lower lid wire."""
        s, q = self.d.split_params(params)
        for side in ("right", "left"):
            u, lo = self.index[f"upper_lid_{side}"], self.index[f"lower_lid_{side}"]
            lower = self.ref(f"lower_lid_{side}") + q[lo]
            target = lower.copy()
            target[:, 1] += 0.02  # rest just on the lower lid
            q[u] = target - self.ref(f"upper_lid_{side}")
        return self.d.join_params(s, q)

    def named(self, name: str) -> np.ndarray:
        table: dict[str, Callable[[], np.ndarray]] = {
            "neutral": lambda: self.rest.copy(),
            "smile": self.smile,
            "surprise": self.surprise,
        }
        return table[name]()


def blink_amount(f: int) -> float:
    """0 (open) .. 1 (closed): each blink closes over BLINK_HALF frames and reopens."""
    a = 0.0
    for c in BLINKS:
        d = abs(f - c)
        if d < BLINK_HALF + 1:
            a = max(a, 1.0 - d / (BLINK_HALF + 1.0))
    return a


def talk_amount(f: int) -> float:
    """Jaw opening while talking: ~4 Hz syllables with a varying amplitude, >= 0."""
    a, b = TALK
    if not a <= f <= b:
        return 0.0
    t = (f - a) / FPS
    env = smoothstep(min(1.0, (f - a) / 8.0)) * smoothstep(min(1.0, (b - f) / 8.0))
    syll = 0.5 - 0.5 * np.cos(2 * np.pi * (4.0 * t + 0.4 * np.sin(2 * np.pi * 0.7 * t)))
    amp = 0.5 + 0.6 * (0.5 + 0.5 * np.sin(2 * np.pi * 0.45 * t + 1.0))
    return float(env * syll * amp)


def script_params(ex: Expressions) -> tuple[np.ndarray, list[str]]:
    """(N_FRAMES, P) wire params and a per-frame label of the scripted expression."""
    keys = [(f, ex.named(n), n) for f, n in KEYFRAMES]
    out = np.zeros((N_FRAMES, len(ex.rest)))
    labels: list[str] = []
    eyes = {"eyes": ex.groups["eyes"]}
    for f in range(N_FRAMES):
        i = max(k for k in range(len(keys) - 1) if keys[k][0] <= f)
        (fa, pa, na), (fb, pb, nb) = keys[i], keys[i + 1]
        t = (f - fa) / (fb - fa)
        p = blend(pa, pb, t, ex.groups)
        label = na if na == nb else f"{na}->{nb}"
        tk = talk_amount(f)
        if tk > 0:
            p = ex.with_q(p, ex.jaw(tk))
            label = "talk"
        bl = blink_amount(f)
        if bl > 0:
            p = blend(p, ex.closed_eyes(p), bl, eyes)
            label = f"{label}+blink" if bl >= 1.0 else label
        out[f] = p
        labels.append(label)
    return out, labels


# -- head motion ----------------------------------------------------------------------


def head_poses(pose0: Pose, person: np.ndarray) -> list[Pose]:
    """Smooth head motion around pose0: yaw/pitch/roll within ~10 deg, +-20 px, +-5 %."""
    pivot = person.mean(axis=0) - np.array([0.0, 2.0, 6.0])  # inside the head, above the neck
    anchor = pose0.apply(pivot[None])[0]
    poses = []
    for f in range(N_FRAMES):
        t = f / FPS
        env = smoothstep(min(1.0, max(0.0, (f - NEUTRAL_END) / 30.0)))
        ph = t - NEUTRAL_END / FPS
        yaw = 9.0 * np.sin(2 * np.pi * 0.13 * ph) + 2.0 * np.sin(2 * np.pi * 0.41 * ph)
        pitch = 6.0 * np.sin(2 * np.pi * 0.19 * ph + 0.5) - 1.5 * np.sin(2 * np.pi * 0.53 * ph)
        roll = 7.0 * np.sin(2 * np.pi * 0.11 * ph + 1.2) * np.sin(2 * np.pi * 0.07 * ph + 0.3)
        head = Rotation.from_euler("yxz", np.array([yaw, pitch, roll]) * env, degrees=True)
        r = pose0.rotation @ head.as_matrix()
        shift = env * np.array(
            [
                18.0 * np.sin(2 * np.pi * 0.09 * ph + 0.7),
                12.0 * np.sin(2 * np.pi * 0.15 * ph),
                0.0,
            ]
        )
        scale = pose0.scale * (1.0 + env * 0.05 * np.sin(2 * np.pi * 0.08 * ph))
        t_vec = anchor + shift - scale * r @ pivot
        poses.append(Pose(r, scale, t_vec))
    return poses


# -- markers --------------------------------------------------------------------------


def marker_views(
    mesh: FaceMesh, rig: Rig, model_vertices: np.ndarray, pose: Pose
) -> tuple[np.ndarray, np.ndarray]:
    """(k, 2) image positions of the rig's markers and (k,) bool: facing the camera."""
    idx = np.array([m.vertex for m in rig.markers])
    img = pose.apply(model_vertices)
    normals = mesh.vertex_normals(model_vertices)[idx] @ pose.rotation.T
    # Image z points away from the camera: a visible surface's normal has negative z.
    visible = -normals[:, 2] > MIN_FACING
    return img[idx, :2], visible


def draw_markers(
    frame: np.ndarray, positions: np.ndarray, visible: np.ndarray, roles: list[str]
) -> None:
    for (x, y), vis, role in zip(positions, visible, roles, strict=True):
        if vis:
            centre = (int(round(x * 16)), int(round(y * 16)))
            cv2.circle(frame, centre, MARKER_RADIUS * 16, ROLE_COLOURS[role], -1, cv2.LINE_AA, 4)


def png_bytes(image: np.ndarray) -> np.ndarray:
    """(k,) uint8: the image PNG-encoded (lossless; cv2.imdecode reads it back)."""
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return np.asarray(buf, dtype=np.uint8).ravel()


# -- main -----------------------------------------------------------------------------


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preview", type=Path, help="also save every 10th frame as PNG here")
    args = ap.parse_args()
    cv2.setNumThreads(1)

    mesh = load_canonical()
    rig = load_rig()
    tracker = LandmarkTracker()
    scene = build_scene(mesh, tracker)
    deformer = WireDeformer.from_rig(scene.person, rig)
    ex = Expressions(deformer)
    params, labels = script_params(ex)
    poses = head_poses(scene.pose0, scene.person)
    roles = [m.role for m in rig.markers]

    k = len(rig.markers)
    marker_xy = np.zeros((N_FRAMES, k, 2))
    marker_vis = np.zeros((N_FRAMES, k), dtype=bool)
    writer = cv2.VideoWriter(str(CLIP), cv2.VideoWriter.fourcc(*"mp4v"), FPS, (WIDTH, HEIGHT))
    if not writer.isOpened():
        raise RuntimeError(f"cannot open a video writer for {CLIP}")
    if args.preview:
        args.preview.mkdir(parents=True, exist_ok=True)
    with FaceRenderer(
        WIDTH, HEIGHT, mesh.triangles, mesh.uvs, scene.texture, scene.background
    ) as renderer:
        for f in range(N_FRAMES):
            v = deformer.deform(params[f])
            frame, _ = renderer.render(poses[f].apply(v))
            xy, vis = marker_views(mesh, rig, v, poses[f])
            marker_xy[f], marker_vis[f] = xy, vis
            draw_markers(frame, xy, vis, roles)
            writer.write(frame)
            if args.preview and f % 10 == 0:
                cv2.imwrite(str(args.preview / f"frame_{f:03d}.png"), frame)
    writer.release()

    np.savez_compressed(
        TRUTH,
        fps=np.int64(FPS),
        width=np.int64(WIDTH),
        height=np.int64(HEIGHT),
        wire_params=params,
        param_names=np.array(deformer.param_names),
        curve_names=np.array(deformer.names),
        curve_features=np.array(deformer.features),
        rotation=np.stack([p.rotation for p in poses]),
        scale=np.array([p.scale for p in poses]),
        translation=np.stack([p.translation for p in poses]),
        marker_xy=marker_xy,
        marker_visible=marker_vis,
        marker_names=np.array([m.name for m in rig.markers]),
        marker_roles=np.array(roles),
        marker_vertices=np.array([m.vertex for m in rig.markers]),
        person_vertices=scene.person,
        texture_png=png_bytes(scene.texture),
        background_png=png_bytes(scene.background),
        landmarks0=scene.landmarks,
        labels=np.array(labels),
        blink_frames=np.array(BLINKS),
        talk_frames=np.array(TALK),
    )
    print(
        f"wrote {CLIP.name} ({CLIP.stat().st_size // 1024} KB) and {TRUTH.name} "
        f"({TRUTH.stat().st_size // 1024} KB): {N_FRAMES} frames, face width "
        f"{np.ptp(scene.landmarks[:, 0]):.0f} px, pose0 {scene.pose0}"
    )


if __name__ == "__main__":
    main()
