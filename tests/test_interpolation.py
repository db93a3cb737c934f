"""Pictures between two received frames, with real frames of the bundled clip and real
rendering: eyes and mouth move on their own curves (seed 000's feature-wise blending: eyes
sqrt(t), mouth t^3), the head turns as a rigid body.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from facewire.loopback import Loopback
from facewire.models.camera import corners_from_homography, homography_from_corners
from facewire.models.face_channels import LIPS as LIPS_CHANNEL
from facewire.models.face_channels import WIRE
from facewire.models.pose import Pose
from facewire.protocol.channels import FrameValues
from facewire.receiver.interpolation import Painter, blend_camera, blend_pose, blend_state
from facewire.sender.capture import VideoSource, demo_clip_path

NEUTRAL, BLINK = 0, 140  # the clip's frame 140: surprise, eyes shut, jaw open
LIDS = ((159, 145), (386, 374))  # upper and lower lid of each eye
LIPS = (13, 14)  # inner upper and lower lip


def _lid_gap(vertices: np.ndarray) -> float:
    return float(sum(np.linalg.norm(vertices[a] - vertices[b]) for a, b in LIDS))


def _mouth_gap(vertices: np.ndarray) -> float:
    return float(np.linalg.norm(vertices[LIPS[0]] - vertices[LIPS[1]]))


@pytest.fixture(scope="module")
def frames():
    """A decoder of a real session and the values of the neutral and the blink frame."""
    from facewire.sender.encoder import FaceEncoder

    with VideoSource(demo_clip_path()) as video:
        clip = list(video.frames(limit=BLINK + 1))
    first = clip[0].image
    # The landmarks as tracked: the lids' geometry must close at the blink for the curves to
    # show. Moved by sender/synthesis.py they close less (the flow matches the snapshot's open
    # eye to a shut one only in part; REM's patch carries the blink): the lids' gap in the
    # model (cm, summed over the lid pairs) then closes by 0.40, not the 0.5 asked below.
    encoder = FaceEncoder(first.shape[1], first.shape[0], 30.0, synthesis=False)
    both = Loopback(encoder, clip[0], seq=None)
    shown: dict[int, FrameValues | None] = {}
    for f in clip:
        both.step(f)
        shown[f.index] = both.shown
    a, blink = shown[NEUTRAL], shown[BLINK]
    assert a is not None and blink is not None
    # The blink frame's expression (wires and the inner lips) with the neutral frame's head and
    # camera: only the face moves between the two.
    b = FrameValues(
        a.seq + 1,
        a.capture_us + 33_333,
        {
            name: (blink.values[name] if name in (WIRE, LIPS_CHANNEL) else v)
            for name, v in a.values.items()
        },
    )
    yield both.decoder, a, b
    both.close()


def test_eyes_and_mouth_move_on_their_own_curves(frames) -> None:
    decoder, a, b = frames
    painter = Painter(decoder)
    ends = [decoder.model(painter.state(v).wires, painter.state(v).lips) for v in (a, b)]
    lids = [_lid_gap(v) for v in ends]
    mouths = [_mouth_gap(v) for v in ends]
    assert lids[0] - lids[1] > 0.5 and mouths[1] - mouths[0] > 0.2  # a blink, an open jaw
    for t in (0.25, 0.5, 0.75):
        state = blend_state(painter.state(a), painter.state(b), t, painter.groups, painter.size)
        between = decoder.model(state.wires, state.lips)
        lid = (_lid_gap(between) - lids[0]) / (lids[1] - lids[0])
        mouth = (_mouth_gap(between) - mouths[0]) / (mouths[1] - mouths[0])
        # Each lies between the two frames, on its feature's curve (other features' wires
        # reach a little into each region).
        assert abs(lid - np.sqrt(t)) < 0.08, (t, lid)
        assert abs(mouth - t**3) < 0.08, (t, mouth)


def test_the_picture_between_shows_the_eyes_ahead_and_the_mouth_behind(frames) -> None:
    decoder, a, b = frames
    painter = Painter(decoder)
    image_a = painter.exact(a).astype(np.int16)
    image_b = painter.exact(b).astype(np.int16)
    middle = painter.between(a, b, 0.5).astype(np.int16)
    vertices = decoder.image_vertices(a)

    def box(indices: list[int]) -> tuple[slice, slice]:
        xy = vertices[indices, :2]
        (x0, y0), (x1, y1) = xy.min(0) - 6, xy.max(0) + 6
        return slice(int(y0), int(y1) + 1), slice(int(x0), int(x1) + 1)

    eyes = box([33, 133, 159, 145, 263, 362, 386, 374])
    mouth = box([61, 291, 0, 17, 13, 14])

    def diff(x: np.ndarray, y: np.ndarray, where: tuple[slice, slice]) -> float:
        return float(np.abs(x[where] - y[where]).mean())

    assert diff(image_a, image_b, eyes) > 2 and diff(image_a, image_b, mouth) > 2
    # Halfway in time the eyes are sqrt(0.5) = 71% shut, the mouth 1/8 open.
    assert diff(middle, image_b, eyes) < diff(middle, image_a, eyes)
    assert diff(middle, image_a, mouth) < diff(middle, image_b, mouth)
    # The ends are the frames themselves.
    assert np.array_equal(painter.between(a, b, 0.0), image_a)
    assert np.array_equal(painter.between(a, b, 1.0), image_b)


def test_the_inner_lips_blend_on_the_mouths_curve(frames) -> None:
    decoder, a, b = frames
    painter = Painter(decoder)
    start, end = painter.state(a), painter.state(b)
    assert np.abs(end.lips - start.lips).max() > 0  # the jaw's opening moved the inner lips
    for t in (0.25, 0.5, 0.75):
        state = blend_state(start, end, t, painter.groups, painter.size)
        assert state.lips == pytest.approx(start.lips + t**3 * (end.lips - start.lips))


def test_the_edge_corrections_move_evenly_between_frames(frames) -> None:
    from dataclasses import replace

    from facewire.models.edge import EDGE_POINTS

    decoder, a, b = frames
    painter = Painter(decoder)
    rng = np.random.default_rng(0)
    start = replace(painter.state(a), edge=rng.uniform(-2, 2, (EDGE_POINTS, 2)))
    end = replace(painter.state(b), edge=rng.uniform(-2, 2, (EDGE_POINTS, 2)))
    for t in (0.25, 0.5, 0.75):
        state = blend_state(start, end, t, painter.groups, painter.size)
        assert state.edge == pytest.approx((1 - t) * start.edge + t * end.edge)


def test_the_head_turns_along_the_shortest_arc() -> None:
    turn_a = Rotation.from_euler("y", -30, degrees=True)
    turn_b = Rotation.from_euler("xy", [20, 50], degrees=True)
    a = Pose((turn_a.as_matrix()), 4.0, np.array([100.0, 50.0, 0.0]))
    b = Pose((turn_b.as_matrix()), 9.0, np.array([300.0, 150.0, 10.0]))
    angle = (turn_a.inv() * turn_b).magnitude()
    for t in (0.1, 0.5, 0.9):
        pose = blend_pose(a, b, t)
        here = Rotation.from_matrix(pose.rotation)
        # On the arc: t of the angle from a, the rest to b.
        assert (turn_a.inv() * here).magnitude() == pytest.approx(t * angle, abs=1e-9)
        assert (here.inv() * turn_b).magnitude() == pytest.approx((1 - t) * angle, abs=1e-9)
        assert pose.scale == pytest.approx(4.0 ** (1 - t) * 9.0**t)
        assert np.allclose(pose.translation, (1 - t) * a.translation + t * b.translation)
    assert blend_pose(a, b, 0.0) is a and blend_pose(a, b, 1.0) is b
    with pytest.raises(ValueError, match=r"blend time must lie in \[0, 1\], got 1.5"):
        blend_pose(a, b, 1.5)


def test_the_scene_moves_with_its_corners() -> None:
    still = np.eye(3)
    moved = homography_from_corners(np.array([8.0, -4, 6, 2]), 640, 480)
    half = blend_camera(still, moved, 0.5, 640, 480)
    assert np.allclose(corners_from_homography(half, 640, 480), [4.0, -2, 3, 1])


def _rings(painter: Painter, a: FrameValues, b: FrameValues, t: float) -> np.ndarray:
    return painter.face_between(a, b, t)[1][painter.mouth.ring_vertices]


def test_the_lips_between_two_frames_follow_the_homotopy_sweep(frames) -> None:
    decoder, a, b = frames
    painter = Painter(decoder)
    ends = [painter.face(v) for v in (a, b)]
    gaps = [_mouth_gap(v) for v in ends]
    assert gaps[1] - gaps[0] > 0.2  # the jaw opens
    rings = painter.mouth.ring_vertices
    assert np.allclose(_rings(painter, a, b, 0.0), ends[0][rings])
    assert np.allclose(_rings(painter, a, b, 1.0), ends[1][rings])
    # From rest at a (no frame before it), halfway in time the sweep is halfway: R_0(1/2) is
    # 1/2 and the control vectors' weights vanish at t = 1/2 (k = 0.5). The mouth's wires
    # alone (t^3) would open it 1/8.
    middle = painter.face_between(a, b, 0.5)[1]
    opened = (_mouth_gap(middle) - gaps[0]) / (gaps[1] - gaps[0])
    assert opened == pytest.approx(0.5, abs=0.05)


def test_the_lips_keep_their_speed_through_a_frame(frames) -> None:
    """Three frames, the lips opening at an even pace: the sweep into the middle frame and
    the sweep out of it meet at the same velocity, the markers' (not at rest, as the
    blending function alone would have them)."""
    decoder, a, b = frames
    values = {
        name: np.round((np.asarray(a.values[name]) + np.asarray(b.values[name])) / 2).astype(
            np.asarray(a.values[name]).dtype
        )
        for name in a.values
    }
    half = FrameValues(b.seq, b.capture_us, values)
    end = FrameValues(b.seq + 1, b.capture_us + 33_333, b.values)
    painter = Painter(decoder)
    painter.exact(a)
    h = 0.01
    arriving = (_rings(painter, a, half, 1.0) - _rings(painter, a, half, 1.0 - h)) / h
    leaving = (_rings(painter, half, end, h) - _rings(painter, half, end, 0.0)) / h
    chord = (
        painter.face(end)[painter.mouth.ring_vertices]
        - painter.face(half)[painter.mouth.ring_vertices]
    )
    speed = np.linalg.norm(chord, axis=1).mean()
    assert np.linalg.norm(arriving, axis=1).mean() > 0.5 * speed
    assert np.linalg.norm(leaving - arriving, axis=1).mean() < 0.2 * speed
