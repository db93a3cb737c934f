"""A first, small version of the snapshot, for a thin link: the picture starts sooner.

The draft is the snapshot itself with its two images made smaller: their sides divided by 2 to
16 and a low WebP quality, lowered until the texture fits in half of ``image_bytes`` and the
background in what the texture left (or the smallest setting is reached). Everything the receiver
decodes frames with (mesh, channel table, reference values, rig) is the same, so the full
snapshot that follows only brings sharper images (docs/protocol.md, 8.7: the receiver swaps
them in). ``meta["texture_size"]`` keeps the full texture's side: the receiver scales the
draft's texture up to it, so REM patches land where they will in the full one.

The full snapshot then comes paced in the datagrams, as one message of at most
MAX_REASSEMBLED bytes (:func:`sharper`). A camera's frame (1280x720 and up) makes a bigger
one: what goes is then the full snapshot with its images re-encoded at a lower quality until
it fits. Where the full snapshot is large (640x480's 33 KB take half a minute of a 24 kbit/s
link), a second draft of about MIDDLE_BYTES goes before it: the picture is sharp in seconds.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging

import cv2
import numpy as np

from facewire.protocol.bundle import MAX_REASSEMBLED
from facewire.protocol.constants import DRAFT
from facewire.protocol.images import decode_image
from facewire.protocol.packets import Snapshot

logger = logging.getLogger(__name__)

#: Divisors of the sides and WebP qualities tried for the draft's images, best first. A 1280x720
#: background takes 1.7 KB at a quarter of its sides (the smallest, once), 0.4 s more of a
#: 24 kbit/s link before the first picture; at a sixteenth it fits.
SCALES = (2, 4, 8, 16)
QUALITIES = (30, 15, 5)
#: The draft's images together take at most this many bytes (the texture, the face, at most
#: half). With the mesh and the rest the draft is then about 2.3 KB at any frame size: 0.8 s of
#: a 24 kbit/s link.
IMAGE_BYTES = 900
#: The second draft's size, bytes, made where the full snapshot is over twice as large.
MIDDLE_BYTES = 10_000
#: Sides' divisors and WebP qualities tried, in turn, for the full snapshot's images when it
#: is too big for the datagrams (the background first: the texture is the face).
PACED_SCALES = (1, 2)
PACED_QUALITIES = (70, 50, 30)


def _smaller(image: np.ndarray, scale: int, quality: int) -> bytes:
    height, width = image.shape[:2]
    size = (max(8, width // scale), max(8, height // scale))
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    ok, data = cv2.imencode(".webp", small, [cv2.IMWRITE_WEBP_QUALITY, quality])
    if not ok:
        raise ValueError("OpenCV could not encode WebP")
    return data.tobytes()


def _within(
    image: np.ndarray, scales: tuple[int, ...], qualities: tuple[int, ...], budget: int
) -> bytes:
    """``image`` as WebP at the first of ``scales`` x ``qualities`` (sides' divisor, quality;
    best first) that takes at most ``budget`` bytes, else at the last. The last is tried first:
    where even it does not fit, no other is encoded (at 640x480, five full-size encodings
    saved for each image that cannot fit)."""
    settings = list(itertools.product(scales, qualities))
    smallest = _smaller(image, *settings[-1])
    if len(smallest) > budget:
        return smallest
    for scale, quality in settings[:-1]:
        data = _smaller(image, scale, quality)
        if len(data) <= budget:
            return data
    return smallest


def draft(snapshot: Snapshot, image_bytes: int = IMAGE_BYTES) -> Snapshot | None:
    """The draft of ``snapshot``, or None when the draft would not be smaller."""
    images: list[bytes] = []
    for name, budget in (("texture", image_bytes // 2), ("background", image_bytes)):
        data = getattr(snapshot, name)
        if data:
            image = decode_image(data, f"snapshot {name}")
            data = _within(image, SCALES, QUALITIES, budget - sum(map(len, images)))
        images.append(data)
    meta = {**snapshot.meta, DRAFT: 1}
    out = dataclasses.replace(snapshot, texture=images[0], background=images[1], meta=meta)
    saved = len(snapshot.texture) + len(snapshot.background) - len(images[0]) - len(images[1])
    if saved <= 0:
        return None
    logger.info("snapshot draft: images %d bytes instead of %d", sum(map(len, images)),
                sum(map(len, images)) + saved)  # fmt: skip
    return out


def paced(snapshot: Snapshot, limit: int = MAX_REASSEMBLED) -> Snapshot | None:
    """The full snapshot as the datagrams carry it: None where ``snapshot`` itself fits in
    ``limit`` bytes, else ``snapshot`` with its background, then its texture, re-encoded
    smaller until it fits (None if even the smallest setting does not)."""
    size = len(bytes(snapshot))
    if size <= limit:
        return None
    images = {"background": snapshot.background, "texture": snapshot.texture}
    # What is not the images (msgpack's bin headers: at most 5 bytes more each).
    rest = size - sum(map(len, images.values())) + 10
    for name, data in images.items():
        if not data:
            continue
        others = sum(len(d) for n, d in images.items() if n != name)
        image = decode_image(data, f"snapshot {name}")
        images[name] = _within(image, PACED_SCALES, PACED_QUALITIES, limit - rest - others)
        if rest + sum(map(len, images.values())) <= limit:
            smaller = dataclasses.replace(
                snapshot, background=images["background"], texture=images["texture"]
            )
            logger.info(
                "the snapshot for the datagrams: %d bytes instead of %d", len(bytes(smaller)), size
            )
            return smaller
    return None


def sharper(snapshot: Snapshot) -> list[Snapshot]:
    """What the datagrams carry after the draft, in order: a second draft of MIDDLE_BYTES
    where the full snapshot is over twice that, then the full snapshot as they can carry it
    (:func:`paced`)."""
    full = paced(snapshot) or snapshot
    if len(bytes(full)) <= 2 * MIDDLE_BYTES:
        return [full]
    middle = paced(snapshot, MIDDLE_BYTES)
    if middle is None:
        return [full]
    return [dataclasses.replace(middle, meta={**snapshot.meta, DRAFT: 1}), full]


def is_draft(snapshot: Snapshot) -> bool:
    return bool(snapshot.meta.get(DRAFT))
