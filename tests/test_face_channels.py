"""The error budget that picks each channel's quantisation step (models/face_channels.py,
sender/encoder.py): what a step moves on screen, measured through the real deformer."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from models.face_channels import (
    HYSTERESIS,
    PEAK_FACTOR,
    POSE_ROTATION,
    POSE_SCALE,
    POSE_TRANSLATION,
    WIRE,
    channel_reach,
    channel_steps,
    load_wire_basis,
    pose_channels,
    pose_from_channels,
)
from models.mesh import load_canonical
from models.pose import FRONTAL, Pose
from models.rig import load_rig
from models.wires import WireDeformer
from sender.capture import CapturedFrame, VideoSource, demo_clip_path
from sender.encoder import TRACKER_RESOLUTION_SHARE, FaceEncoder

SCALE = 12.0  # px per cm: a face about 200 px wide


@pytest.fixture(scope="module")
def face() -> tuple[WireDeformer, np.ndarray, Pose]:
    vertices = load_canonical().vertices
    wires = WireDeformer.from_rig(vertices, load_rig())
    rest = wires.rest_params()
    basis = load_wire_basis()
    displacements = np.stack([wires.displacement(rest + b) for b in basis.vectors])
    pose = Pose(FRONTAL, SCALE, np.array([320.0, 240.0, 0.0]))
    return wires, displacements, pose


def _moved(face, channel: str, index: int, amount: float) -> np.ndarray:
    """Per-vertex screen displacement, px, of one channel value moved by ``amount``."""
    wires, _, pose = face
    basis = load_wire_basis()
    rest = wires.rest_params()
    values = {**pose_channels(pose), WIRE: np.zeros(basis.size)}
    before = pose_from_channels(values).apply(wires.deform(rest + basis.params(values[WIRE])))
    values[channel] = values[channel].copy()
    values[channel][index] += amount
    after = pose_from_channels(values).apply(wires.deform(rest + basis.params(values[WIRE])))
    return np.linalg.norm((after - before)[:, :2], axis=1)


@pytest.mark.parametrize("error_px", [0.2, 0.5])
def test_each_value_keeps_the_budget_on_screen(face, error_px: float) -> None:
    wires, displacements, _ = face
    steps = channel_steps(channel_reach(wires.base_vertices, displacements, SCALE), error_px)
    worst = 0.5 + HYSTERESIS  # steps a value may be off with the sender's hysteresis
    sizes = {POSE_ROTATION: 3, POSE_SCALE: 1, POSE_TRANSLATION: 2, WIRE: len(displacements)}
    for channel, size in sizes.items():
        rms, peak = [], []
        for i in range(size):
            moved = _moved(face, channel, i, worst * steps[channel])
            rms.append(np.sqrt(np.mean(moved**2)))
            peak.append(moved.max())
        assert max(rms) <= error_px * 1.02, (channel, max(rms))
        assert max(peak) <= PEAK_FACTOR * error_px * 1.02, (channel, max(peak))
        # ... and no finer than it needs: one of the two bounds is met by some value.
        tight = max(max(rms) / error_px, max(peak) / (PEAK_FACTOR * error_px))
        assert tight > 0.97, (channel, tight)


def test_the_head_position_gets_the_finest_step_of_the_face(face) -> None:
    # A translation step moves every vertex; a wire coefficient's, a part of the face: under
    # an RMS budget the position is quantised finer than its largest displacement alone asks.
    wires, displacements, _ = face
    reach = channel_reach(wires.base_vertices, displacements, SCALE)
    assert reach.rms[POSE_TRANSLATION] == reach.peak[POSE_TRANSLATION] == 1.0
    assert reach.rms[WIRE] < 0.5 * reach.peak[WIRE]
    steps = channel_steps(reach, 0.2)
    assert steps[POSE_TRANSLATION] == pytest.approx(0.2 / (0.5 + HYSTERESIS))
    assert steps[WIRE] * reach.peak[WIRE] > 2 * steps[POSE_TRANSLATION]


def test_channel_steps_refuse_a_budget_that_is_no_budget(face) -> None:
    wires, displacements, _ = face
    reach = channel_reach(wires.base_vertices, displacements, SCALE)
    with pytest.raises(ValueError, match="must be > 0"):
        channel_steps(reach, 0.0)
    with pytest.raises(ValueError, match="no face"):
        channel_reach(np.zeros((0, 3)), displacements, SCALE)


def _first_frame(size: tuple[int, int] | None) -> CapturedFrame:
    with VideoSource(demo_clip_path()) as video:
        image = next(iter(video.frames(limit=1))).image
    if size is not None:
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    return CapturedFrame(0, image, 0)


def test_a_large_face_is_coded_as_finely_as_the_tracker_resolves() -> None:
    # The bundled clip's face is about 220 px high: a pixel of the landmark model's 192-px
    # input is about 1.7 image pixels, so the budget rises above 0.2 px. A QCIF-sized copy of
    # the same frame (a 55-px face) keeps the asked-for budget.
    large = _first_frame(None)
    encoder = FaceEncoder(large.image.shape[1], large.image.shape[0], 30.0, rem=False)
    assert encoder.start(large) is not None
    assert 0.25 < encoder.budget_px < 0.35
    assert encoder.budget_px == pytest.approx(TRACKER_RESOLUTION_SHARE * 1.5 * 223 / 192, 0.1)
    small = _first_frame((176, 132))
    encoder = FaceEncoder(176, 132, 30.0, rem=False, error_px=0.2)
    assert encoder.start(small) is not None
    assert encoder.budget_px == 0.2
