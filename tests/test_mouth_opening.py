"""The inner lips' opening (models/mouth_opening.py): two GDEs part what the wires cannot."""

from __future__ import annotations

import numpy as np
import pytest

from models.mesh import load_canonical
from models.mouth_opening import INNER_LIP_VERTICES, LIPS_SIZE, MouthOpening
from models.rig import load_rig
from models.wires import WireDeformer
from protocol.packets import DeltaFrame, KeyFrame, decode
from receiver.decoder import FaceDecoder
from sender.capture import CapturedFrame, VideoSource, demo_clip_path
from sender.encoder import FaceEncoder

UPPER, LOWER = INNER_LIP_VERTICES
OUTER_LOWER = 17  # the lower lip's outer edge, below LOWER
#: MediaPipe's lower inner lip, corner to corner.
LOWER_INNER_LIP = [95, 88, 178, 87, 14, 317, 402, 318, 324]


def _gap(points: np.ndarray) -> float:
    return float(points[LOWER, 1] - points[UPPER, 1])


def test_each_element_moves_its_own_lip() -> None:
    mesh = load_canonical()
    mouth = MouthOpening(mesh, load_rig())
    assert np.all(mouth.displacement(np.zeros(LIPS_SIZE)) == 0)
    # The lower inner lip down by 0.5 cm (model y is up): it moves all the way, the upper
    # lip not at all (the mouth's seam parts them), the outer edge of the lower lip less.
    moved = mouth.displacement(np.array([0.0, -0.5]))
    assert moved[LOWER] == pytest.approx([0.0, -0.5, 0.0], abs=0.03)  # (lambda's give)
    assert np.abs(moved[UPPER]).max() < 1e-9
    assert 0 <= -moved[OUTER_LOWER, 1] < 0.5
    # The values are what the wires leave at the two centres, up and down (y).
    tracked = mesh.vertices.copy()
    tracked[UPPER, :2] += (0.1, 0.2)
    tracked[LOWER, 1] -= 0.3
    assert mouth.values(tracked, mesh.vertices) == pytest.approx([0.2, -0.3])
    with pytest.raises(ValueError, match="lips values"):
        mouth.displacement(np.zeros(3))


def test_the_wires_cannot_part_the_inner_lips_and_the_elements_do() -> None:
    # The lower inner lip dropped by 0.4 cm, the rest of the face still: the wires' best fit
    # (seed 000's least squares) parts the lips by less than half of it; with the two
    # elements on what they leave, the lips part as far as the target.
    mesh = load_canonical()
    rig = load_rig()
    wires = WireDeformer.from_rig(mesh.vertices, rig)
    wires.prepare_fit()
    target = mesh.vertices.copy()
    target[LOWER_INNER_LIP, 1] -= 0.4
    fitted = wires.deform(wires.fit(target))
    mouth = MouthOpening(mesh, rig)
    opened = fitted + mouth.displacement(mouth.values(target, fitted))
    rest = -_gap(mesh.vertices)  # model y is up: the gap is upper minus lower there
    assert -_gap(fitted) - rest < 0.5 * 0.4
    assert -_gap(opened) - rest == pytest.approx(0.4, abs=0.06)


def test_an_open_jaw_is_rebuilt_as_open_as_tracked() -> None:
    """The bundled clip's surprise opens the jaw (frames 112-150): the receiver's inner lips
    part as far as the tracker saw them part. (The clip was made by the wires, so they could
    part its lips alone; on real footage they cannot: BENCHMARKS.md, "The inner lips".)"""
    with VideoSource(demo_clip_path()) as video:
        frames = [
            CapturedFrame(f.index, f.image, round(f.index * 1e6 / video.fps))
            for f in video.frames(limit=150)
        ]
    encoder = FaceEncoder(640, 480, 30.0, rem=False)
    snapshot = encoder.start(frames[0])
    assert snapshot is not None
    decoder = FaceDecoder(decode(bytes(snapshot)))  # type: ignore[arg-type]
    try:
        widest = (0.0, 0.0)  # tracked, rebuilt
        shown = None
        for frame in frames:
            packet = encoder.encode(frame)
            if packet is not None:
                decoded = decode(bytes(packet))
                assert isinstance(decoded, (KeyFrame, DeltaFrame))
                shown = decoder.decode(decoded)
            assert shown is not None and encoder.points is not None
            tracked = _gap(encoder.points)
            if tracked > widest[0]:
                widest = (tracked, _gap(decoder.image_vertices(shown)))
    finally:
        decoder.close()
    tracked, rebuilt = widest
    assert tracked > 15, widest  # the jaw did open
    assert abs(rebuilt - tracked) < 0.1 * tracked, widest
