"""Sender encoder -> packet bytes -> receiver decoder, against the bundled clip's ground truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from facewire.loopback import Loopback
from facewire.models.face_channels import LIPS, WIRE, pose_from_channels
from facewire.protocol.packets import PacketError
from facewire.receiver.decoder import FaceDecoder, SnapshotError
from facewire.sender.capture import VideoSource, demo_clip_path

# neutral, smile, surprise with a blink, talking. Blinks are left out of the marker check: the
# clip's closed eye is a squashed open one, which the trackers read as half open
# (benchmarks/bench_eyes.py and bench_call.py measure it).
FRAMES = [0, 60, 140, 220]


@pytest.fixture(scope="module")
def clip() -> tuple[list, dict]:
    truth = dict(np.load(demo_clip_path().with_name("demo_clip_truth.npz")))
    with VideoSource(demo_clip_path()) as video:
        frames = list(video.frames(limit=max(FRAMES) + 1))
    return frames, truth


@pytest.fixture(scope="module")
def call(clip: tuple[list, dict]) -> dict[str, dict[int, np.ndarray]]:
    """Image-space vertices per frame of FRAMES: "rebuilt" by the receiver from the packets,
    "intended" by the sender (its fit, reduced to the wire basis and smoothed over time, before
    quantisation) and "fit" (the sender's full wire fit)."""
    return _call(clip, synthesis=True)


@pytest.fixture(scope="module")
def tracked_call(clip: tuple[list, dict]) -> dict[str, dict[int, np.ndarray]]:
    """:func:`call` from the landmarks as tracked, not moved by sender/synthesis.py."""
    return _call(clip, synthesis=False)


def _call(clip: tuple[list, dict], synthesis: bool) -> dict[str, dict[int, np.ndarray]]:
    from facewire.sender.encoder import FaceEncoder

    frames, truth = clip
    # No rate cap: these tests hold the coding to its error budget, frame by frame, and a
    # frame the cap holds back (tests/test_rate_cap.py) shows the frame before it. The
    # bundled clip's 1.49 kbit/s sits at the cap: here it held the surprise's frame 140.
    encoder = FaceEncoder(
        int(truth["width"]),
        int(truth["height"]),
        float(truth["fps"]),
        geometry_kbps=None,
        synthesis=synthesis,
    )
    both = Loopback(encoder, frames[0], seq=None)
    decoder = both.decoder
    assert encoder.wires is not None
    out: dict[str, dict[int, np.ndarray]] = {
        k: {}
        for k in (
            "rebuilt",
            "intended",
            "fit",
            "rebuilt_model",
            "fit_model",
            "intended_model",
            "reduced_model",
        )
    }
    try:
        for f in frames:  # track every frame: the tracker follows from frame to frame
            result = encoder.analyse(f.image)
            # Nothing sent: nothing changed, the receiver keeps the last frame.
            if both.receive(both.send_analysed(f, result)):
                assert both.shown is not None and both.shown.seq == f.index
            shown = both.shown
            if f.index in FRAMES:
                assert shown is not None and result is not None
                pose, params = result
                reduced = encoder.rest_params + encoder.basis.params(encoder.projected(params))
                meant = encoder.intended  # the values quantised: smoothed
                assert meant is not None
                meant_params = encoder.rest_params + encoder.basis.params(meant[WIRE])
                out["rebuilt"][f.index] = decoder.image_vertices(shown)
                out["rebuilt_model"][f.index] = decoder.model(*decoder.parameters(shown)[1:])
                # What the sender meant: its wires and the inner lips' opening, unquantised.
                assert encoder.mouth is not None
                meant_model = encoder.wires.deform(meant_params) + encoder.mouth.displacement(
                    meant[LIPS]
                )
                out["intended"][f.index] = pose_from_channels(meant).apply(meant_model)
                out["intended_model"][f.index] = meant_model
                out["fit"][f.index] = pose.apply(encoder.wires.deform(params))
                # Expression alone (model space, cm): what the basis keeps of the full fit.
                out["fit_model"][f.index] = encoder.wires.deform(params)
                out["reduced_model"][f.index] = encoder.wires.deform(reduced)
    finally:
        both.close()
    return out


@pytest.fixture(scope="module")
def rebuilt(call: dict[str, dict[int, np.ndarray]]) -> dict[int, np.ndarray]:
    return call["rebuilt"]


def test_the_call_rebuilds_what_the_sender_meant_within_the_error_budget(call) -> None:
    # Four channels (rotation, scale, translation, wire basis) each move a vertex at most
    # 0.5 px by quantisation (plus hysteresis of a quarter step).
    for i in FRAMES:
        err = np.linalg.norm((call["rebuilt"][i] - call["intended"][i])[:, :2], axis=1)
        assert np.sqrt(np.mean(err**2)) < 1.0 and err.max() < 3.0, (i, err.max())
        # The expression alone (model space, cm): quantisation adds about 0.02 cm RMS, while
        # a quarter of the expression (0.19-0.26 cm RMS of motion here) would be 0.05-0.07.
        model = np.linalg.norm(call["rebuilt_model"][i] - call["intended_model"][i], axis=1)
        assert np.sqrt(np.mean(model**2)) < 0.04, (i, np.sqrt(np.mean(model**2)))


def test_the_wire_basis_keeps_the_expression(tracked_call) -> None:
    # The 16-vector basis against the full 225-parameter fit: the expression's motion from
    # the neutral first frame, in model space (head motion left out), is kept. Of the tracked
    # landmarks: the moves sender/synthesis.py adds (where the texture matches, not an
    # expression) the basis keeps only in part (the talking frame 220 loses 56 % of its
    # motion with them, 19 % without), and the tests against the truth below take them in.
    for i in FRAMES[1:]:
        full = tracked_call["fit_model"][i] - tracked_call["fit_model"][0]
        reduced = tracked_call["reduced_model"][i] - tracked_call["reduced_model"][0]
        lost = np.sqrt(np.mean(np.sum((full - reduced) ** 2, axis=1)))
        moved = np.sqrt(np.mean(np.sum(full**2, axis=1)))
        assert lost < 0.25 * moved, (i, lost, moved)


def test_rebuilt_markers_land_on_the_true_markers(clip, rebuilt) -> None:
    _, truth = clip
    vertices = truth["marker_vertices"]
    lids = np.isin(vertices, [159, 145, 386, 374])
    errors = []
    for i in FRAMES:
        visible = truth["marker_visible"][i] & ~(lids if i == 140 else False)
        err = np.linalg.norm(rebuilt[i][vertices, :2] - truth["marker_xy"][i], axis=1)[visible]
        assert np.median(err) < 6.0, (i, np.round(err, 1))
        errors.append(err)
    # Faces are ~200 px wide: a few pixels is a few per cent of the face.
    pooled = np.concatenate(errors)
    assert np.median(pooled) < 4.0 and pooled.max() < 14.0, np.round(pooled, 1)


def _corner_drop(points: np.ndarray) -> float:
    """How far (px) the mouth corners sit below the nose tip."""
    return float((points[61, 1] + points[291, 1]) / 2 - points[1, 1])


def _mouth_gap(points: np.ndarray) -> float:
    return float(points[14, 1] - points[13, 1])


def test_expressions_survive_the_call(rebuilt) -> None:
    # Smile (frame 60): corners rise by ~15 px in the truth; the call keeps most of it.
    assert _corner_drop(rebuilt[60]) < _corner_drop(rebuilt[0]) - 5.0
    # Surprise (frame 140): the jaw opens, the corners drop.
    assert _mouth_gap(rebuilt[140]) > _mouth_gap(rebuilt[0]) + 4.0
    assert _corner_drop(rebuilt[140]) > _corner_drop(rebuilt[0]) + 5.0


def test_a_lost_frame_holds_the_face_instead_of_snapping_to_neutral(clip) -> None:
    # The tracker finds nothing in a black frame in the middle of the smile. The receiver
    # keeps showing the smile (the last values, within the error budget), and the face
    # comes back with the next frame.
    from facewire.sender.encoder import FaceEncoder

    frames, truth = clip
    blank = 62
    encoder = FaceEncoder(int(truth["width"]), int(truth["height"]), float(truth["fps"]))
    shown_at: dict[int, np.ndarray] = {}
    with Loopback(encoder, frames[0], seq=None) as both:
        for f in frames[: blank + 3]:
            image = np.zeros_like(f.image) if f.index == blank else f.image
            both.step(dataclasses.replace(f, image=image))
            assert both.shown is not None
            shown_at[f.index] = both.decoder.image_vertices(both.shown)
    assert encoder.frames_untracked == 1
    held = np.linalg.norm((shown_at[blank] - shown_at[blank - 1])[:, :2], axis=1)
    assert held.max() < 1.5, held.max()
    assert _corner_drop(shown_at[blank]) < _corner_drop(shown_at[0]) - 5.0  # still smiling
    back = np.linalg.norm((shown_at[blank + 2] - shown_at[blank - 1])[:, :2], axis=1)
    assert np.median(back) < 3.0, np.median(back)


def test_decoder_refuses_a_snapshot_of_another_rig(clip) -> None:
    from facewire.sender.encoder import FaceEncoder

    frames, truth = clip
    encoder = FaceEncoder(int(truth["width"]), int(truth["height"]), float(truth["fps"]))
    snapshot = encoder.start(frames[0])
    assert snapshot is not None
    import dataclasses

    other = dataclasses.replace(snapshot, rig_hash="0" * 64)
    with pytest.raises(SnapshotError, match="differs from this receiver's"):
        FaceDecoder(other)


def test_decoder_survives_empty_and_refuses_huge_images(clip) -> None:
    import dataclasses
    import struct
    import zlib

    from facewire.sender.encoder import FaceEncoder

    frames, truth = clip
    encoder = FaceEncoder(int(truth["width"]), int(truth["height"]), float(truth["fps"]))
    snapshot = encoder.start(frames[0])
    assert snapshot is not None
    # Empty images are allowed by the format: the receiver shows grey instead of crashing.
    empty = dataclasses.replace(snapshot, texture=b"", background=b"")
    decoder = FaceDecoder(empty)
    try:
        assert decoder.background.shape == (snapshot.height, snapshot.width, 3)
    finally:
        decoder.close()
    # A tiny PNG whose header claims 16384 x 16384 is refused before any pixel is decoded: a
    # snapshot that carries it can be neither built nor decoded.
    ihdr = struct.pack(">IIBBBBB", 16384, 16384, 8, 2, 0, 0, 0)
    chunk = b"IHDR" + ihdr
    png = (
        b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + chunk + struct.pack(">I", zlib.crc32(chunk))
    )
    with pytest.raises(PacketError, match="16384x16384"):
        dataclasses.replace(snapshot, texture=png)
