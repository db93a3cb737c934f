"""The inner lips' opening (models/mouth_opening.py): seed 003's mouth rig moves the inner
contour where the wires cannot."""

from __future__ import annotations

import numpy as np
import pytest

from facewire.loopback import Loopback
from facewire.models.mesh import load_canonical
from facewire.models.mouth_opening import LIPS_SIZE, MouthOpening
from facewire.models.rig import load_rig
from facewire.models.wires import WireDeformer
from facewire.sender.capture import CapturedFrame, VideoSource, demo_clip_path
from facewire.sender.encoder import FaceEncoder

UPPER, LOWER = 13, 14  # the inner lips' centres: the top and bottom markers of the contour
OUTER_LOWER = 17  # the lower lip's outer edge, below LOWER
#: MediaPipe's lower inner lip, corner to corner.
LOWER_INNER_LIP = [78, 95, 88, 178, 87, 14, 317, 402, 318, 324, 308]
BOTTOM_Y = 7  # the bottom marker's y among the channel's values (x, then y, of l, t, r, b)


def _gap(points: np.ndarray) -> float:
    return float(points[LOWER, 1] - points[UPPER, 1])


def test_the_bottom_marker_moves_the_lower_lip_and_not_the_outer_contour() -> None:
    mesh = load_canonical()
    rig = load_rig()
    mouth = MouthOpening(mesh, rig)
    assert np.all(mouth.displacement(np.zeros(LIPS_SIZE)) == 0)
    values = np.zeros(LIPS_SIZE)
    values[BOTTOM_Y] = -0.5  # the lower inner lip's centre down by 0.5 cm (model y is up)
    moved = mouth.displacement(values)
    assert moved[LOWER] == pytest.approx([0.0, -0.5, 0.0], abs=1e-12)
    assert abs(moved[UPPER, 1]) < 1e-12
    # The outer contour stays the wires'; the rings between follow 2/3 and 1/3 of the way.
    assert np.abs(moved[list(rig.lips.contours[0])]).max() == 0
    assert moved[OUTER_LOWER, 1] == 0
    middle = [rig.lips.contours[1][15], rig.lips.contours[2][15]]  # below the centre
    assert moved[middle, 1] == pytest.approx([-0.5 / 3, -1.0 / 3], abs=1e-12)
    # Along the lower lip it falls off smoothly from the centre to the corners: no vertex
    # beside the centre is left where the wires put it.
    dy = moved[LOWER_INNER_LIP, 1]
    assert dy[0] == pytest.approx(0, abs=1e-12) and dy[-1] == pytest.approx(0, abs=1e-12)
    assert np.all(np.diff(dy[:6]) < 0) and np.all(np.diff(dy[5:]) > 0)
    assert np.all(dy[2:-2] < -0.25)
    with pytest.raises(ValueError, match="lips values"):
        mouth.displacement(np.zeros(3))


def test_the_values_are_what_the_wires_leave_on_the_inner_contour() -> None:
    mesh = load_canonical()
    mouth = MouthOpening(mesh, load_rig())
    rng = np.random.default_rng(3)
    values = rng.normal(scale=0.2, size=LIPS_SIZE)
    tracked = mesh.vertices + mouth.displacement(values)
    assert mouth.values(tracked, mesh.vertices) == pytest.approx(values, abs=1e-9)


def test_a_mouth_open_in_an_o_is_rebuilt_as_an_o() -> None:
    # The lower inner lip dropped in an arc, 0.4 cm at its centre, the rest of the face
    # still (a shout, as on carphone): the wires' best fit (seed 000's least squares)
    # parts the lips by less than half of it; with the mouth rig on what they leave, every
    # vertex of the lower inner lip reaches the arc, not only its centre.
    mesh = load_canonical()
    rig = load_rig()
    wires = WireDeformer.from_rig(mesh.vertices, rig)
    wires.prepare_fit()
    target = mesh.vertices.copy()
    x = mesh.vertices[LOWER_INNER_LIP, 0]
    drop = 0.4 * (1 - (x / np.abs(x).max()) ** 2)
    target[LOWER_INNER_LIP, 1] -= drop
    fitted = wires.deform(wires.fit(target))
    mouth = MouthOpening(mesh, rig)
    opened = fitted + mouth.displacement(mouth.values(target, fitted))
    rest = -_gap(mesh.vertices)  # model y is up: the gap is upper minus lower there
    assert -_gap(fitted) - rest < 0.5 * 0.4
    assert -_gap(opened) - rest == pytest.approx(0.4, abs=0.06)
    assert np.abs(opened[LOWER_INNER_LIP, 1] - target[LOWER_INNER_LIP, 1]).max() < 0.06


def test_an_open_jaw_is_rebuilt_as_open_as_tracked() -> None:
    """The bundled clip's surprise opens the jaw (frames 112-150): the receiver's inner lips
    part as far as the tracker saw them part. (The clip was made by the wires, so they could
    part its lips alone; on real footage they cannot: docs/what-we-tried.md, "The inner lips
    from the mouth rig".)"""
    with VideoSource(demo_clip_path()) as video:
        frames = [
            CapturedFrame(f.index, f.image, round(f.index * 1e6 / video.fps))
            for f in video.frames(limit=150)
        ]
    encoder = FaceEncoder(640, 480, 30.0, rem=False)
    widest = (0.0, 0.0)  # tracked, rebuilt
    with Loopback(encoder, frames[0], seq=None) as both:
        for frame in frames:
            both.step(frame)
            assert both.shown is not None and encoder.points is not None
            tracked = _gap(encoder.points)
            if tracked > widest[0]:
                widest = (tracked, _gap(both.decoder.image_vertices(both.shown)))
    tracked, rebuilt = widest
    assert tracked > 15, widest  # the jaw did open
    assert abs(rebuilt - tracked) < 0.1 * tracked, widest
