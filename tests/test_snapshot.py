"""The snapshot fits the face: texture resolution follows the face's size, images are WebP."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from facewire.protocol import mesh_code
from facewire.protocol.images import decode_image, image_size
from facewire.sender.capture import CapturedFrame
from facewire.sender.encoder import MAX_TEXTURE_SIZE, MIN_TEXTURE_SIZE, FaceEncoder, texture_size

ASTRONAUT = Path(__file__).parent / "fixtures" / "astronaut_face.jpg"


def test_texture_side_is_the_power_of_two_the_face_can_fill() -> None:
    assert texture_size(60) == 128  # a QCIF call's face: two texels a pixel
    assert texture_size(185) == 512  # the bundled clip's, before the byte budget
    assert texture_size(185, 1.25) == 256  # the least it gets
    assert texture_size(10) == MIN_TEXTURE_SIZE
    assert texture_size(4000) == MAX_TEXTURE_SIZE


def test_a_small_face_gets_a_small_texture_and_both_images_are_webp() -> None:
    face = cv2.imread(str(ASTRONAUT))
    for scale, side in ((0.5, 64), (0.75, 128), (1.0, 128)):  # faces 47, 70, 94 px wide
        image = cv2.resize(face, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        h, w = image.shape[:2]
        snapshot = FaceEncoder(w, h, 30.0).start(CapturedFrame(0, image, 0))
        assert snapshot is not None
        assert image_size(snapshot.texture) == ("webp", side, side)
        assert image_size(snapshot.background) == ("webp", w, h)
        background = decode_image(snapshot.background, "background")
        # Quality: the background is the frame itself, seen at the call's size.
        assert cv2.PSNR(background, image) > 30.0
        assert np.isfinite(snapshot.vertices).all()


def test_a_qcif_snapshot_keeps_its_budget_and_both_ends_share_the_mesh() -> None:
    from facewire.protocol.packets import decode

    face = cv2.imread(str(ASTRONAUT))
    frame = cv2.resize(face, (176, 144), interpolation=cv2.INTER_AREA)
    encoder = FaceEncoder(176, 144, 30.0)
    snapshot = encoder.start(CapturedFrame(0, frame, 0))
    assert snapshot is not None and encoder.session is not None
    assert len(bytes(snapshot)) <= 12_000  # issue 8's budget for a 176x144 call
    # The mesh coded against the canonical one: under half of float16's 2808 bytes.
    assert snapshot.meta["vertex_step"] == mesh_code.STEP_CM == 0.005
    assert len(snapshot.vertex_bytes()) < 1400
    received = decode(bytes(snapshot))
    assert isinstance(received, type(snapshot))
    # The sender fits on the very mesh the receiver deforms.
    assert np.array_equal(received.vertices.astype(np.float64), encoder.session.mesh.vertices)
