"""The bundled demo clip (tools/make_demo_clip.py) and its ground truth agree."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
from imaging import psnr

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from facewire.models.mesh import load_canonical  # noqa: E402
from facewire.models.pose import Pose  # noqa: E402
from facewire.models.rig import load_rig  # noqa: E402
from facewire.models.wires import WireDeformer  # noqa: E402

DATA = Path(__file__).resolve().parents[1] / "sender" / "data"
CLIP = DATA / "demo_clip.mp4"
TRUTH = DATA / "demo_clip_truth.npz"
N, W, H, FPS = 300, 640, 480, 30
SURPRISE = 135  # a frame inside the held surprise
TRACKED = (0, 60, SURPRISE, 200)


@pytest.fixture(scope="module")
def truth() -> dict[str, np.ndarray]:
    with np.load(TRUTH) as z:
        return {k: z[k] for k in z.files}


@pytest.fixture(scope="module")
def clip(truth) -> dict[int, np.ndarray]:
    """The decoded frames the tests look at, by frame number (and the frame count)."""
    cap = cv2.VideoCapture(str(CLIP))
    assert cap.isOpened(), f"cannot open {CLIP}"
    want = {0, SURPRISE, *TRACKED, *truth["blink_frames"].tolist()}
    frames: dict[int, np.ndarray] = {}
    n = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        if n in want:
            frames[n] = frame
        n += 1
    frames[-1] = np.array(n)
    cap.release()
    return frames


@pytest.fixture(scope="module")
def deformer(truth) -> WireDeformer:
    return WireDeformer.from_rig(truth["person_vertices"], load_rig())


def pose(truth, f: int) -> Pose:
    return Pose(truth["rotation"][f], float(truth["scale"][f]), truth["translation"][f])


def test_clip_opens_with_expected_format(clip):
    cap = cv2.VideoCapture(str(CLIP))
    assert int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)) == W
    assert int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT)) == H
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(FPS)
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == N
    cap.release()
    assert int(clip[-1]) == N
    assert clip[0].shape == (H, W, 3)
    assert CLIP.stat().st_size < 1_600_000


def test_truth_is_consistent(truth, deformer):
    rig = load_rig()
    k = len(rig.markers)
    p = deformer.n_params
    assert int(truth["fps"]) == FPS
    assert truth["wire_params"].shape == (N, p)
    assert list(truth["param_names"]) == deformer.param_names
    assert list(truth["curve_names"]) == [c.name for c in rig.curves]
    assert truth["rotation"].shape == (N, 3, 3)
    assert truth["scale"].shape == (N,)
    assert truth["translation"].shape == (N, 3)
    assert truth["marker_xy"].shape == (N, k, 2)
    assert truth["marker_visible"].shape == (N, k)
    assert list(truth["marker_names"]) == [m.name for m in rig.markers]
    assert list(truth["marker_roles"]) == [m.role for m in rig.markers]
    assert truth["person_vertices"].shape == (468, 3)
    assert len(truth["labels"]) == N
    # Frame 0 is the person at rest, and the first second is still.
    np.testing.assert_array_equal(truth["wire_params"][0], deformer.rest_params())
    np.testing.assert_allclose(truth["wire_params"][:30], truth["wire_params"][:1].repeat(30, 0))
    np.testing.assert_allclose(truth["translation"][:30], truth["translation"][:1].repeat(30, 0))
    # Marker positions are the projected mesh vertices.
    for f in (0, SURPRISE):
        img = pose(truth, f).apply(deformer.deform(truth["wire_params"][f]))
        np.testing.assert_allclose(
            truth["marker_xy"][f], img[truth["marker_vertices"], :2], atol=1e-9
        )


def test_rerendered_frames_match_the_clip(truth, clip, deformer):
    from facewire.receiver.render import FaceRenderer

    mesh = load_canonical()
    tex = cv2.imdecode(truth["texture_png"], cv2.IMREAD_COLOR)
    bg = cv2.imdecode(truth["background_png"], cv2.IMREAD_COLOR)
    with FaceRenderer(W, H, mesh.triangles, mesh.uvs, tex, bg) as r:
        for f in (0, SURPRISE):
            out, mask = r.render(pose(truth, f).apply(deformer.deform(truth["wire_params"][f])))
            inside = cv2.erode(mask.astype(np.uint8), np.ones((5, 5), np.uint8)).astype(bool)
            dots = np.zeros((H, W), np.uint8)  # the marker dots are drawn on top: leave out
            for (x, y), vis in zip(truth["marker_xy"][f], truth["marker_visible"][f], strict=True):
                if vis:
                    cv2.circle(dots, (int(round(x)), int(round(y))), 6, 1, -1)
            inside &= dots == 0
            assert inside.sum() > 20_000
            assert psnr(out[inside], clip[f][inside]) > 28, f"frame {f}"
            assert psnr(out, clip[f]) > 26, f"frame {f} (whole)"


def test_tracker_finds_the_face_at_the_pose_markers(truth, clip):
    from facewire.sender.landmarks import LandmarkTracker

    tracker = LandmarkTracker()
    pose_idx = np.flatnonzero(truth["marker_roles"] == "pose")
    verts = truth["marker_vertices"][pose_idx]
    for f in TRACKED:
        tracker.reset()
        tracker.track(clip[f])
        lm = tracker.track(clip[f])  # second pass: the tracker's own crop
        assert lm is not None, f"frame {f}"
        err = np.linalg.norm(lm.points[verts, :2] - truth["marker_xy"][f, pose_idx], axis=1)
        assert np.median(err) < 3.0, f"frame {f}: {np.round(err, 1)}"
        assert err.max() < 8.0, f"frame {f}: {np.round(err, 1)}"


def test_scripted_expressions_are_there(truth, deformer):
    params = truth["wire_params"]
    rest = deformer.deform(params[0])

    def lid_gap(v: np.ndarray) -> float:  # mean upper-to-lower lid distance, both eyes, cm
        return float(np.mean([v[159, 1] - v[145, 1], v[386, 1] - v[374, 1]]))

    gap0 = lid_gap(rest)
    assert gap0 > 0.2
    for f in truth["blink_frames"]:
        assert lid_gap(deformer.deform(params[f])) < 0.15 * gap0, f"blink at {f}"
        assert "blink" in str(truth["labels"][f])
    # Surprise: brows up, eyes wide, mouth open.
    v = deformer.deform(params[SURPRISE])
    brows = [105, 334]
    assert np.all(v[brows, 1] - rest[brows, 1] > 0.4)
    assert lid_gap(v) > gap0 + 0.05
    assert (v[0, 1] - v[17, 1]) - (rest[0, 1] - rest[17, 1]) > 0.5
    # Smile: lip corners up.
    v = deformer.deform(params[60])
    assert np.all(v[[61, 291], 1] - rest[[61, 291], 1] > 0.3)
    # Talking: the mouth opens and closes several times.
    a, b = truth["talk_frames"]
    gap = np.array([deformer.deform(params[f])[[0, 17], 1] @ [1, -1] for f in range(a, b)])
    opening = gap - (rest[0, 1] - rest[17, 1])
    assert opening.max() > 0.4
    crossings = np.count_nonzero(np.diff((opening > 0.5 * opening.max()).astype(int)) == 1)
    assert crossings >= 6
    # Back to neutral at the end.
    np.testing.assert_allclose(params[-1], params[0], atol=1e-12)
